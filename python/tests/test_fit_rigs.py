"""The FIRS, display, BRRDF and DISCO fits from Python against the files the same fit wrote when
the quick demo ran it (read here with NumPy from their documented layouts)."""

import json
import pathlib

import numpy as np
import pytest

import lightrig


def test_disco_f_is_the_demo_s(demos, tmp_path):
    d = demos("disco")
    m = lightrig.fit_disco(d / "session", out=tmp_path)
    n = len(m["vertices"])
    F = m["F"]
    assert F.shape == (n, n, 3) and F.dtype == np.float32 and F.flags.c_contiguous
    assert m["observed"].shape == (n, n) and m["observed"].dtype == np.bool_
    assert m["triangles"].dtype == np.uint32 and m["triangles"].max() < n
    # F.f32: the upper triangle, for k in 0..n, r in k..n: F(r, k) as 3 little-endian f32.
    meta = json.loads((d / "fit" / "F.json").read_text())
    assert meta["vertices"] == n
    upper = np.fromfile(d / "fit" / "F.f32", dtype="<f4").reshape(-1, 3)
    k, r = np.triu_indices(n)
    np.testing.assert_allclose(F[k, r], upper, rtol=1e-5, atol=0)
    np.testing.assert_allclose(F, F.transpose(1, 0, 2), rtol=0, atol=0)
    bits = np.unpackbits(np.fromfile(d / "fit" / "F-observed.bits", dtype=np.uint8), bitorder="little")[: len(k)]
    assert (m["observed"][k, r] == bits.astype(bool)).all()
    assert sorted(pathlib.Path(f).name for f in m["files"]) == sorted(p.name for p in (d / "fit").iterdir() if not p.name.startswith("relit-truth"))
    assert 0.5 < m["beam_sigma_mm"] < 1.5 and m["used"] + m["missed"] + m["held_out_frames"] == m["frames"]


def test_brrdf_bins_are_the_demo_s(demos):
    d = demos("brrdf")
    m = lightrig.fit_brrdf(d / "spheres" / "session", spectralon=d / "spectralon" / "session")
    pairs = m["pairs"]
    assert pairs.ndim == 2 and pairs.shape[1] == 2 and pairs.dtype == np.uint16
    assert m["files"] == []
    for s in m["spheres"]:
        header = json.loads((d / "fit" / f"brrdf-{s['name']}.json").read_text())
        n = header["bins"]
        assert header["pairs"] == pairs.tolist()
        raw = np.fromfile(d / "fit" / header["values"], dtype="<f4").reshape(n, n, n, len(pairs))
        assert s["bins"].shape == raw.shape
        np.testing.assert_allclose(s["bins"], raw, rtol=1e-5, atol=1e-7)
        assert (s["bin_counts"] > 0).sum() == header["observed_bins"]
        ns = len(s["light_deg"])
        assert s["values"].shape == (ns, len(pairs)) and s["angles"].shape == (ns, 3) and s["pixels"].shape == (ns, 2)


def test_display_calibration_is_the_demo_s(demos):
    d = demos("display")
    m = lightrig.fit_display(d / "calibration" / "session")
    assert m["kind"] == "calibration"
    demo_cal = json.loads((d / "calibration" / "display-calibration.json").read_text())
    assert m["calibration"]["axes"][0]["coil"] == demo_cal["axes"][0]["coil"]
    for a, b in zip(m["calibration"]["axes"], demo_cal["axes"]):
        np.testing.assert_allclose(a["frequencies_hz"], b["frequencies_hz"], rtol=1e-12)
        np.testing.assert_allclose(a["response_m"], b["response_m"], rtol=1e-9)
    shown = lightrig.fit_display(d / "display" / "session", calibration=d / "calibration" / "display-calibration.json")
    assert shown["kind"] == "shown" and shown["shown"]
    for s in shown["shown"]:
        assert len(s["target"]) == len(s["shown"]) == 2
        assert all(abs(e) < 0.2 for e in s["error"]), s


def read_ply_vertices(path):
    """The vertex count and positions of a PLY lightrig wrote (binary or ASCII)."""
    data = pathlib.Path(path).read_bytes()
    head, _, body = data.partition(b"end_header\n")
    lines = head.decode().splitlines()
    n = next(int(l.split()[2]) for l in lines if l.startswith("element vertex"))
    fmt = next(l.split()[1] for l in lines if l.startswith("format"))
    props = [l.split() for l in lines if l.startswith("property") and "list" not in l]
    return n, fmt, props, body


def test_firs_surface_points_are_the_demo_s(demos):
    d = demos("firs-sphere") / "sphere"
    m = lightrig.fit_firs_surface(d / "session")
    pts = m["points"]
    assert pts.ndim == 2 and pts.shape[1] == 3 and pts.dtype == np.float64 and len(pts) > 1000
    summary = json.loads((d / "fit" / "summary.json").read_text())
    assert summary  # the demo's own fit summary, for its counts
    plys = sorted((d / "fit").glob("*.ply"))
    assert plys, "the demo wrote its points as PLY"
    n, fmt, props, body = read_ply_vertices(plys[0])
    assert n == len(pts), (plys[0], n, len(pts))
    h, w = m["height"], m["width"]
    assert all(s["points"].shape == (h, w, 3) for s in m["scans"])


def test_firs_volume_is_the_demo_s(demos):
    d = demos("firs-volume") / "volume"
    m = lightrig.fit_firs_volume(d / "session")
    occ = m["occupancy"]
    meta = json.loads((d / "fit" / "volume.json").read_text())
    raw = np.fromfile(d / "fit" / "volume.raw", dtype="<f4").reshape(occ.shape)
    np.testing.assert_allclose(occ, raw, rtol=1e-6, atol=1e-7)
    assert occ.dtype == np.float32 and 0.0 <= occ.min() and occ.max() <= 1.0
    assert len(m["vertices"]) > 100 and m["triangles"].shape[1] == 3 and m["enclosed_mm3"] > 0
    assert meta

"""The FIRS, display, BRRDF and DISCO fits from Python against the files the same fit wrote when
the quick demo ran it (read here with NumPy from their documented layouts)."""

import json
import pathlib

import numpy as np
import OpenEXR
import pytest

import lightrig


def test_disco_f_is_the_demo_s(demos, tmp_path):
    d = demos("disco")
    m = lightrig.fit_disco(d / "session", out=tmp_path)
    n = len(m["vertices"])
    F = m["F"]
    assert F.shape == (n, n, 3) and F.dtype == np.float32 and F.flags.c_contiguous
    # The fit's own buffer handed to NumPy, reshaped as a view: F (n² × 3 floats) is not copied.
    assert not F.flags.owndata and F.base.ndim == 1 and F.base.size == F.size and not F.base.flags.owndata
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
    assert sorted(pathlib.Path(f).name for f in m["files"]) == sorted(p.name for p in (d / "fit").iterdir() if not p.name.startswith(("relit-truth", "relit-figure")))
    assert 0.5 < m["beam_sigma_mm"] < 1.5 and m["used"] + m["missed"] + m["held_out_frames"] == m["frames"]
    # The local term: each texture as its EXR (read by the OpenEXR package), the atlas and the
    # spots as atlas.json and fit.json say.
    atlas = json.loads((d / "fit" / "atlas.json").read_text())
    assert m["atlas"] == atlas
    h, w = atlas["height"], atlas["width"]
    for name in ("kernel-rates", "kernel-c1", "kernel-c2", "kernel-correction", "detail"):
        t = m["textures"][name]
        assert t.shape == (h, w, 3) and t.dtype == np.float32, name
        ch = OpenEXR.File(str(d / "fit" / f"{name}.exr"), separate_channels=True).channels()
        np.testing.assert_array_equal(t, np.stack([ch[c].pixels for c in "RGB"], axis=-1), err_msg=name)
    covered = m["covered"]
    assert covered.shape == (h, w) and covered.dtype == np.bool_
    assert (m["textures"]["detail"][~covered] == 0).all() and (m["textures"]["detail"][covered] > 0).all()
    rates = m["textures"]["kernel-rates"]
    assert (m["kernel_observed"] == (rates[..., 2] == 1)).all() and not (m["kernel_observed"] & ~covered).any()
    fit_json = json.loads((d / "fit" / "fit.json").read_text())
    assert m["spots"] == fit_json["local"]["spots"]
    # The scanned mesh as read and checked: the demo's own binary PLY, the pebble's icosphere.
    assert {k: v for k, v in m["scan"].items() if k != "file"} == {k: v for k, v in fit_json["scan"].items() if k != "file"}
    assert pathlib.Path(m["scan"]["file"]).resolve() == (d / "object.ply").resolve()
    assert m["scan"]["format"] == "PLY (binary, little-endian)" and m["scan"]["vertices"] == n
    assert m["scan"]["boundary_edges"] == 0 and m["scan"]["area_spread_p95_over_p5"] < m["scan"]["area_spread_limit"]
    assert sum(s["kept"] for s in m["spots"]) == m["local_spots"] == fit_json["local"]["spots_fitted"]
    assert int(m["kernel_observed"].sum()) == fit_json["local"]["observed_texels"]
    assert int(m["detail_observed"].sum()) == fit_json["detail"]["observed_texels"]


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
        assert 0.0 <= s["shape_error"] < 0.5, s


def test_a_fit_takes_set_as_the_command_takes_it(demos):
    """``set=`` changes the session's rig file for the fit alone, as ``lightrig fit --set`` does:
    the screen said 60 mm away instead of 50 reads every tilt 50/60 as large."""
    d = demos("display")
    cal = d / "calibration" / "display-calibration.json"
    plain = lightrig.fit_display(d / "display" / "session", calibration=cal)
    far = lightrig.fit_display(d / "display" / "session", calibration=cal, set=["plan.screen.distance_mm=60"])
    assert len(plain["shown"]) == len(far["shown"]) > 0
    for a, b in zip(plain["shown"], far["shown"]):
        for k in range(2):
            assert abs(b["shown"][k] / a["shown"][k] / (50 / 60) - 1) < 0.05, (a, b)
    # A key that describes how the session was taken is refused, naming it and what to do.
    with pytest.raises(lightrig.FitError, match="acquire again") as e:
        lightrig.fit_display(d / "display" / "session", calibration=cal, set=["plan.exposure_us=5"])
    assert "plan.exposure_us" in str(e.value)
    with pytest.raises(lightrig.FitError, match="expected KEY=VALUE"):
        lightrig.fit_display(d / "display" / "session", calibration=cal, set=["plan.screen.distance_mm"])
    # One string alone is not taken for a list of its characters.
    with pytest.raises(lightrig.LightrigError, match="give a list"):
        lightrig.fit_display(d / "display" / "session", calibration=cal, set="plan.screen.distance_mm=60")


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
    assert summary["merged_points"] == len(pts) and summary["image"] == [m["width"], m["height"]]
    assert summary["ray_pixels"] == m["ray_pixels"] and summary["sheet_samples"] == m["sheet_samples"]
    assert summary["sheet_rms_mm"] == pytest.approx(m["sheet_rms_mm"], rel=1e-12)
    # merged.ply: the same points, as float32 (binary little endian, x y z).
    n, fmt, props, body = read_ply_vertices(d / "fit" / "merged.ply")
    assert fmt == "binary_little_endian" and [p[1:] for p in props] == [["float", "x"], ["float", "y"], ["float", "z"]]
    ply = np.frombuffer(body[: 12 * n], dtype="<f4").reshape(n, 3)
    np.testing.assert_allclose(ply, pts, rtol=0, atol=1e-5 * np.abs(pts).max())
    h, w = m["height"], m["width"]
    assert [s["angle_deg"] for s in m["scans"]] == [o["angle_deg"] for o in summary["orientations"]]
    for s, o in zip(m["scans"], summary["orientations"]):
        assert s["points"].shape == (h, w, 3) and int(np.isfinite(s["points"][..., 0]).sum()) == o["points"]


def test_firs_volume_is_the_demo_s(demos):
    d = demos("firs-volume") / "volume"
    m = lightrig.fit_firs_volume(d / "session")
    occ = m["occupancy"]
    meta = json.loads((d / "fit" / "volume.json").read_text())
    raw = np.fromfile(d / "fit" / "volume.raw", dtype="<f4").reshape(occ.shape)
    np.testing.assert_allclose(occ, raw, rtol=1e-6, atol=1e-7)
    assert occ.dtype == np.float32 and 0.0 <= occ.min() and occ.max() <= 1.0
    assert len(m["vertices"]) > 100 and m["triangles"].shape[1] == 3 and m["enclosed_mm3"] > 0
    # volume.json: the grid the array is laid out on, x fastest: (z, y, x).
    assert meta["order"] == "x-fastest" and meta["dtype"] == "float32" and meta["endian"] == "little"
    assert list(occ.shape) == meta["dims"][::-1]
    np.testing.assert_allclose(m["voxel_mm"], meta["voxel_mm"], rtol=1e-12)
    np.testing.assert_allclose(m["origin_mm"], meta["origin_mm"], rtol=1e-12)
    n, *_ = read_ply_vertices(d / "fit" / "volume.ply")
    assert n == len(m["vertices"])

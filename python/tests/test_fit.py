"""Each fit from Python against the `lightrig fit` command's own files on the same session
(read back with the OpenEXR package, not lightrig's reader), its errors against the command's
message, its progress and its interruption by Ctrl-C."""

import json
import os
import pathlib
import subprocess
import sys
import textwrap

import numpy as np
import OpenEXR
import pytest

import lightrig
from conftest import run_cli


def exr_channels(path):
    """`{"layer.channel": pixels}` of a multi-part EXR (one part per layer, as lightrig writes)."""
    f = OpenEXR.File(str(path), separate_channels=True)
    return {f"{part.name()}.{c}": ch.pixels for part in f.parts for c, ch in part.channels.items()}


@pytest.fixture(scope="module")
def lls_both(lls_dir, tmp_path_factory):
    """The LLS fit of the demo's session from Python (writing its files) and from the command."""
    tmp = tmp_path_factory.mktemp("lls-fit")
    cal = lls_dir / "camera.toml"
    m = lightrig.fit_lls(lls_dir / "session", calibration=cal, out=tmp / "py")
    code, out, err = run_cli("fit", "lls", lls_dir / "session", "--calibration", cal, "--out", tmp / "cli")
    assert code == 0, err
    return m, tmp / "cli", out


def test_lls_maps_are_the_command_s(lls_both):
    m, cli_dir, _ = lls_both
    h, w = m["height"], m["width"]
    cli = exr_channels(cli_dir / "maps.exr")
    fitted = m["fitted"]
    assert fitted.shape == (h, w) and fitted.dtype == np.bool_ and fitted.sum() > 0.5 * h * w
    for key, layer in (("diffuse", "diffuse"), ("specular", "specular")):
        a = m[key]
        assert a.shape == (h, w, 3) and a.dtype == np.float32 and a.flags.c_contiguous
        assert not a.flags.owndata and not a.base.flags.owndata  # the fit's buffer, not a copy
        for c, ch in enumerate("RGB"):
            np.testing.assert_allclose(a[..., c][fitted], cli[f"{layer}.{ch}"][fitted], rtol=1e-6, atol=0)
        assert np.isnan(a[~fitted]).all()
    np.testing.assert_allclose(m["alpha"][fitted], cli["roughness.Y"][fitted], rtol=1e-6)
    np.testing.assert_allclose(m["translucency"], cli["translucency.Y"], rtol=1e-6)
    have = ~np.isnan(m["points"][..., 2])
    np.testing.assert_allclose(m["points"][..., 2][have], cli["height.Y"][have], rtol=1e-6, atol=1e-9)
    n = m["normals"]
    ok = ~np.isnan(n[..., 0])
    for c, ch in enumerate("XYZ"):
        np.testing.assert_allclose(n[..., c][ok], cli[f"normal.{ch}"][ok], rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(np.linalg.norm(n[ok], axis=-1), 1.0, atol=1e-5)


def test_lls_masks_and_checks_are_the_command_s(lls_both):
    m, cli_dir, cli_out = lls_both
    cli = exr_channels(cli_dir / "maps.exr")
    for name in ("reflectance", "roughness", "height", "translucency", "physical"):
        mask = m["valid"][name]
        assert mask.dtype == np.bool_ and mask.shape == (m["height"], m["width"])
        np.testing.assert_array_equal(mask, cli[f"valid.{name}.Y"] == 1.0)
    np.testing.assert_array_equal(m["valid"]["reflectance"], m["fitted"])
    # (pythonize gives fixed-size arrays as tuples, JSON as lists)
    assert json.loads(json.dumps(m["quality"])) == json.loads((cli_dir / "quality.json").read_text())
    assert m["quality"]["fitted"]["pixels"] == int(m["fitted"].sum())
    assert m["quality"]["roughness_determined"]["pixels"] == int(m["valid"]["roughness"].sum())
    assert "fitted %d of %d pixels" % (m["fitted"].sum(), m["height"] * m["width"]) in cli_out


def test_lls_writes_the_command_s_files(lls_both):
    m, cli_dir, cli_out = lls_both
    listed = [pathlib.Path(l) for l in cli_out.splitlines() if l.startswith(str(cli_dir))]
    assert sorted(pathlib.Path(f).name for f in m["files"]) == sorted(p.name for p in listed)
    assert all(pathlib.Path(f).is_file() for f in m["files"])


def test_lls_without_out_leaves_nothing(lls_dir, tmp_path, monkeypatch):
    calls = []
    m = lightrig.fit_lls(lls_dir / "session", calibration=lls_dir / "camera.toml", progress=lambda d, t: calls.append((d, t)))
    assert m["files"] == []
    assert calls and all(0 <= d <= t for d, t in calls) and calls[-1][0] == calls[-1][1]
    assert [d for d, _ in calls] == sorted(d for d, _ in calls)


def test_a_progress_callback_s_exception_stops_the_fit(lls_dir):
    def progress(done, total):
        raise ValueError(f"stop at {done}")

    with pytest.raises(ValueError, match="stop at"):
        lightrig.fit_lls(lls_dir / "session", calibration=lls_dir / "camera.toml", progress=progress)


def test_ctrl_c_interrupts_a_fit_and_removes_its_scratch(lls_dir, tmp_path):
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    script = textwrap.dedent(
        f"""
        import os, signal, lightrig
        seen = []
        def progress(done, total):
            if not seen:
                seen.append(done)
                print("started", flush=True)
                os.kill(os.getpid(), signal.SIGINT)  # as Ctrl-C in a terminal or a notebook's stop
        lightrig.fit_lls({str(lls_dir / 'session')!r}, calibration={str(lls_dir / 'camera.toml')!r}, progress=progress)
        print("finished", flush=True)
        """
    )
    env = dict(os.environ, TMPDIR=str(scratch))
    p = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300)
    assert p.stdout.splitlines() == ["started"], p.stdout + p.stderr
    # Python ends on an uncaught KeyboardInterrupt by the signal itself (a shell reports 130).
    assert p.returncode == -2 and p.stderr.rstrip().endswith("KeyboardInterrupt"), p.stderr
    assert list(scratch.iterdir()) == []


@pytest.mark.parametrize("pipeline", ["disco", "brrdf", "firs-surface", "firs-volume", "display"])
def test_a_session_of_another_rig_raises_the_command_s_message(lls_session, pipeline, tmp_path):
    code, _, err = run_cli("fit", pipeline, lls_session, "--out", tmp_path / "cli")
    assert code == 1
    with pytest.raises(lightrig.FitError) as e:
        lightrig.fit(pipeline, lls_session)
    assert err.strip() == f"error: {e.value}".strip()


def test_an_unknown_pipeline():
    with pytest.raises(lightrig.LightrigError, match="the pipelines are: lls, firs-surface"):
        lightrig.fit("nope", ".")

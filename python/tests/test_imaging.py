"""Image files against the OpenEXR package and pypng, HDR merging and response recovery against
a camera simulated here in NumPy, calibration against the `lightrig calibrate` command."""

import glob
import pathlib

import numpy as np
import OpenEXR
import png
import pytest

import lightrig
from conftest import run_cli

RNG = np.random.default_rng(7)


def test_exr_round_trip_and_an_independent_reader(tmp_path):
    a = RNG.random((5, 7, 3), dtype=np.float32) * 10
    p = tmp_path / "a.exr"
    lightrig.write_image(p, a, precision="float")
    back, bits = lightrig.read_image(p)
    assert bits == 32 and back.dtype == np.float32 and back.shape == (5, 7, 3)
    np.testing.assert_array_equal(back, a)
    ch = OpenEXR.File(str(p), separate_channels=True).channels()
    np.testing.assert_array_equal(np.stack([ch[c].pixels for c in "RGB"], axis=-1), a)


def test_an_exr_another_tool_wrote_is_read(tmp_path):
    y = RNG.random((4, 6), dtype=np.float32)
    p = tmp_path / "other.exr"
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, {"Y": y}).write(str(p))
    back, bits = lightrig.read_image(p)
    assert back.shape == (4, 6)
    np.testing.assert_array_equal(back, y)


def test_png_16_bit_against_pypng(tmp_path):
    a = (np.arange(12 * 9, dtype=np.float32).reshape(9, 12) / (12 * 9 - 1))
    p = tmp_path / "a.png"
    lightrig.write_image(p, a, bits=16)
    w, h, rows, info = png.Reader(filename=str(p)).read_flat()
    assert (w, h, info["bitdepth"], info["planes"]) == (12, 9, 16, 1)
    np.testing.assert_array_equal(np.asarray(rows).reshape(9, 12), np.round(a * 65535).astype(np.uint16))
    back, bits = lightrig.read_image(p)
    assert bits == 16
    np.testing.assert_allclose(back, a, atol=0.5 / 65535)


def test_float64_input_is_taken_as_float32(tmp_path):
    p = tmp_path / "d.exr"
    lightrig.write_image(p, np.full((2, 3), 0.25), precision="half")
    assert (lightrig.read_image(p)[0] == 0.25).all()


def test_bad_image_input(tmp_path):
    with pytest.raises(lightrig.ImageError, match="give .height, width. or .height, width, channels."):
        lightrig.write_image(tmp_path / "x.exr", np.zeros((2, 2, 7)))
    with pytest.raises(lightrig.ImageError, match="write .exr, .png or .tif"):
        lightrig.write_image(tmp_path / "x.jpg", np.zeros((2, 2)))
    (tmp_path / "junk.png").write_bytes(b"not an image")
    with pytest.raises(lightrig.ImageError, match="junk.png"):
        lightrig.read_image(tmp_path / "junk.png")


def test_spectral_exr_in_fichet_s_layout(tmp_path):
    diag = {500.0: RNG.random((3, 4), dtype=np.float32), 550.5: RNG.random((3, 4), dtype=np.float32)}
    rerad = {(450.0, 550.5): RNG.random((3, 4), dtype=np.float32)}
    p = tmp_path / "s.exr"
    lightrig.write_spectral_exr(p, diag, rerad)
    ch = OpenEXR.File(str(p), separate_channels=True).channels()
    assert set(ch) == {"T.500nm", "T.550,5nm", "T.450nm.550,5nm"}
    np.testing.assert_array_equal(ch["T.550,5nm"].pixels, diag[550.5])
    back = lightrig.read_spectral_exr(p)
    assert (back["width"], back["height"]) == (4, 3)
    for k, v in diag.items():
        np.testing.assert_array_equal(back["diagonal"][k], v)
    np.testing.assert_array_equal(back["reradiation"][(450.0, 550.5)], rerad[(450.0, 550.5)])
    with pytest.raises(lightrig.ImageError, match="every plane has one size"):
        lightrig.write_spectral_exr(tmp_path / "t.exr", {500.0: np.zeros((3, 4), np.float32), 510.0: np.zeros((2, 4), np.float32)})


def camera(radiance, times, gamma=1.0, levels=65535):
    """A camera simulated here: level = round(levels * clip(E t)^(1/gamma))."""
    return [np.round(levels * np.clip(radiance * t, 0, 1) ** (1 / gamma)).astype(np.uint16 if levels > 255 else np.uint8) for t in times]


def test_hdr_merge_of_a_linear_camera_recovers_the_radiance():
    e = np.exp(RNG.uniform(np.log(0.5), np.log(2000), (40, 50))).astype(np.float64)
    times = [1e-4, 1e-3, 1e-2, 1e-1]
    images = camera(e, times)
    radiance, unreliable = lightrig.hdr_merge(images, times)
    assert radiance.shape == e.shape and radiance.dtype == np.float32 and unreliable.dtype == np.bool_
    assert not unreliable.any()
    # Levels per unit time: the radiance in the camera's own units (65535 per unit E·t).
    np.testing.assert_allclose(radiance / 65535, e, rtol=2e-3)


def test_hdr_merge_marks_samples_clipped_in_every_exposure():
    e = np.array([[1.0, 1e6]])
    radiance, unreliable = lightrig.hdr_merge(camera(e, [0.1, 0.5]), [0.1, 0.5])
    assert unreliable.tolist() == [[False, True]]


def test_hdr_response_of_a_gamma_camera():
    # 8-bit, gamma 2.2: ln f^-1(z) = 2.2 ln(z/255) up to a constant.
    e = np.exp(RNG.uniform(np.log(0.02), np.log(50), (60, 60)))
    times = [1 / 64, 1 / 16, 1 / 4, 1.0, 4.0]
    g = lightrig.hdr_response(camera(e, times, gamma=2.2, levels=255), times)
    assert g.shape == (1, 256) and g.dtype == np.float32
    z = np.arange(40, 220)
    expected = 2.2 * np.log(z / 255.0)
    got = g[0, z] - g[0, 128] + 2.2 * np.log(128 / 255.0)
    assert np.max(np.abs(got - expected)) < 0.05
    # Merged through it, a third exposure series gives the radiance to a scale.
    radiance, unreliable = lightrig.hdr_merge(camera(e, times, gamma=2.2, levels=255), times, response=g.tolist())
    ratio = radiance[~unreliable] / e[~unreliable]
    assert np.std(np.log(ratio)) < 0.02


def test_hdr_errors():
    with pytest.raises(lightrig.ImageError, match="image 1 has shape"):
        lightrig.hdr_merge([np.zeros((2, 2), np.uint8), np.zeros((3, 2), np.uint8)], [1, 2])
    with pytest.raises(lightrig.ImageError):
        lightrig.hdr_merge([np.zeros((2, 2), np.uint8)], [1])


SAMPLES = sorted(glob.glob("/usr/share/doc/opencv-doc/examples/data/left0*.jpg"))


@pytest.mark.skipif(len(SAMPLES) < 5, reason="OpenCV's sample chessboards (Debian's opencv-doc, which CI installs)")
def test_calibrate_is_the_command_s(tmp_path):
    files = SAMPLES[:6]
    c = lightrig.calibrate(files, 9, 6, 25.0, skip_missing=True, out=tmp_path / "py.toml")
    code, _, err = run_cli("calibrate", *files, "--cols", "9", "--rows", "6", "--square", "25", "--skip-missing", "--out", tmp_path / "cli.toml")
    assert code == 0, err
    import tomllib

    cli = tomllib.loads((tmp_path / "cli.toml").read_text())
    py_file = tomllib.loads((tmp_path / "py.toml").read_text())
    assert py_file == c
    assert c["intrinsics"] == cli["intrinsics"] and c["distortion"] == cli["distortion"]
    assert c["fit"] == cli["fit"] and c["view"] == cli["view"]
    assert 500 < c["intrinsics"]["fx"] < 560

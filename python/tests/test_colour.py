"""The BRRDF fit's spectral EXRs read by colour-science (`colour.read_spectral_image_Fichet2021`,
through OpenImageIO), as a user of another spectral tool reads them: the per-pixel images
(`spectral-<angle>deg.exr`) and each sphere's reradiation matrix (`reradiation-<sphere>.exr`,
one pixel per PCA angle). What is shared with lightrig: nothing of the reading (colour's own
parser of the layout's channel names, OpenImageIO's EXR decoder); the samples compared with come
from `lightrig.fit_brrdf`."""

import warnings

import numpy as np
import pytest

with warnings.catch_warnings():
    # colour warns at import about the optional SciPy and Matplotlib, which these reads need not.
    warnings.simplefilter("ignore")
    import colour


@pytest.fixture(scope="module")
def brrdf(demos):
    import lightrig

    d = demos("brrdf")
    return d, lightrig.fit_brrdf(d / "spheres" / "session", spectralon=d / "spectralon" / "session")


def read(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return colour.read_spectral_image_Fichet2021(str(path), additional_data=True)


def entries(components):
    """`{(λi, λo): values}` from colour's components (`T` the diagonal, else by excitation)."""
    out = {}
    for key, (wl, v) in components.items():
        for k, lo in enumerate(wl):
            li = lo if key == "T" else float(key)
            out[(float(li), float(lo))] = v[..., k]
    return out


def test_colour_reads_each_spheres_reradiation_matrix_as_the_fits_median(brrdf):
    d, m = brrdf
    pairs = [tuple(map(float, p)) for p in m["pairs"]]
    angles = m["pca_angles"]
    for s in m["spheres"]:
        comp, spec = read(d / "fit" / f"reradiation-{s['name']}.exr")
        assert spec.is_bispectral and not spec.is_emissive
        got = entries(comp)
        assert sorted(got) == sorted(pairs)
        light = np.asarray(s["light_deg"])
        for j, p in enumerate(pairs):
            assert got[p].shape == (1, len(angles))
            want = [np.median(s["values"][light == a, j]) * np.pi for a in angles]
            np.testing.assert_allclose(got[p][0], want, rtol=1e-6, atol=1e-9)


def test_the_fluorescent_sphere_reradiates_blue_into_green(brrdf):
    # The yellow fluorescent coat absorbs blue and re-emits green: its largest entry off the
    # diagonal is excited at 460 nm or below and emitted from 500 to 560 nm. Every pair off the
    # diagonal emits at a longer wavelength (Stokes; the plan measures no other). The orange
    # coat does not fluoresce: beyond the neighbouring band (where the filters' bands overlap
    # and its steep reflectance edge leaks, 1.2 % at 580→600 nm on the quick demo) its entries
    # stay under 1 % of the fluorescent peak.
    d, _ = brrdf
    fl = entries(read(d / "fit" / "reradiation-bottom.exr")[0])
    orange = entries(read(d / "fit" / "reradiation-top.exr")[0])
    assert all(o > i for (i, o) in fl if o != i) and all(o > i for (i, o) in orange if o != i)
    peak, (pi_, po) = max((float(v.max()), k) for k, v in fl.items() if k[0] != k[1])
    assert peak > 0.1 and pi_ <= 460 and 500 <= po <= 560, (peak, pi_, po)
    far = max(float(np.abs(v).max()) for (i, o), v in orange.items() if o - i > 20)
    assert far < 0.01 * peak, (far, peak)


def test_colour_reads_the_per_pixel_images_as_the_fits_samples(brrdf):
    d, m = brrdf
    pairs = [tuple(map(float, p)) for p in m["pairs"]]
    a = m["pca_angles"][0]
    comp, spec = read(d / "fit" / f"spectral-{a:.0f}deg.exr")
    assert spec.is_bispectral
    got = entries(comp)
    assert sorted(got) == sorted(pairs)
    for s in m["spheres"]:
        at = np.asarray(s["light_deg"]) == a
        xy = np.asarray(s["pixels"])[at]
        for j, p in enumerate(pairs):
            np.testing.assert_allclose(got[p][xy[:, 1], xy[:, 0]], s["values"][at, j] * np.pi, rtol=1e-6, atol=1e-9)

"""The LLS fit's Mitsuba 3 export (`fit/mitsuba/scene.xml`) rendered by Mitsuba 3 itself (PyPI,
CPU variant `scalar_rgb`) as a user renders it, against the virtual camera's image of the true
sample under the same light (`truth/point-light.exr`, the scene's own Ward materials) and against
lightrig's own image of its GGX fit (`fit/relit-point.exr`). What Mitsuba shares with lightrig:
nothing of the code (its GGX, its camera, its texture lookups are its own); the light position
and intensity come from the exported file."""

import pathlib
import shutil

import mitsuba as mi
import numpy as np
import OpenEXR
import pytest

mi.set_variant("scalar_rgb")


def parts(path):
    """`{part name: {channel group: pixels}}` of a lightrig EXR."""
    f = OpenEXR.File(str(path))
    return {p.name(): {k: np.array(v.pixels) for k, v in p.channels.items()} for p in f.parts}


def render(xml):
    return np.array(mi.render(mi.load_file(str(xml))))


@pytest.fixture(scope="module")
def images(lls_dir):
    truth = parts(lls_dir / "truth" / "truth.exr")
    lit = np.array(OpenEXR.File(str(lls_dir / "truth" / "point-light.exr")).channels()["RGB"].pixels)
    ours = parts(lls_dir / "fit" / "relit-point.exr")
    # The sample's pixels whose 3 × 3 neighbourhood is one material: away from the tiles' edges,
    # where a pixel's area (Mitsuba's box filter) and its centre (the truth's ray) see different
    # materials.
    region, rough = truth["region"]["Y"], truth["roughness"]["Y"]
    h, w = region.shape
    interior = np.zeros((h, w), bool)
    for y in range(1, h - 1):
        for x in range(1, w - 1):
            interior[y, x] = (region[y - 1 : y + 2, x - 1 : x + 2] == 1).all() and (
                rough[y - 1 : y + 2, x - 1 : x + 2] == rough[y, x]
            ).all()
    ggx = ours["ggx"]["RGB"]
    mask = interior & (ggx.sum(-1) > 0)
    assert mask.sum() > 1000, mask.sum()
    return lit, ggx, ours["ward"]["RGB"], mask


def errors(a, b, mask):
    """Median and 95th percentile of |Σa / Σb − 1| (RGB summed) over `mask`."""
    e = np.abs(a.sum(-1)[mask] / b.sum(-1)[mask] - 1)
    return float(np.median(e)), float(np.percentile(e, 95))


def test_mitsuba_renders_the_ggx_export_as_lightrig_and_the_truth_see_it(lls_dir, images):
    lit, ggx, ward, mask = images
    img = render(lls_dir / "fit" / "mitsuba" / "scene.xml")
    assert img.shape == lit.shape
    # Against lightrig's own image of the same fit: the export's conventions (camera, texture
    # orientation, normal map, the blend's factors of 2, GGX's α and G). Measured on the quick
    # demo: median 0.74 %, 95th percentile 4.7 % (the textures lie on a flat plane at the
    # fitted points' median height, the sample's bumps do not: parallax in the highlight).
    med, p95 = errors(img, ggx, mask)
    assert med < 0.015 and p95 < 0.08, (med, p95)
    # Against the true sample (Ward materials; GGX fitted to them): the GGX fit's own error
    # under this light. Measured: median 4.4 %, 95th percentile 17.6 %, as lightrig's own
    # GGX image (4.4 %, 17.3 %); the Ward fit's is 1.1 % and 5.4 %.
    med_t, p95_t = errors(img, lit, mask)
    assert med_t < 0.06 and p95_t < 0.25, (med_t, p95_t)
    ours = errors(ggx, lit, mask)
    assert abs(med_t - ours[0]) < 0.01, (med_t, ours)
    assert errors(ward, lit, mask)[0] < 0.02


def test_a_wrong_texture_orientation_is_caught(lls_dir, images, tmp_path):
    # The check can fail: the same export with its textures flipped top to bottom (the other
    # common convention for v) is far off lightrig's image.
    _, ggx, _, mask = images
    src = lls_dir / "fit" / "mitsuba"
    for f in src.iterdir():
        shutil.copy(f, tmp_path / f.name)
    for name in ("diffuse.exr", "specular.exr", "alpha.exr", "normal.exr"):
        bmp = np.array(mi.Bitmap(str(src / name)))
        mi.Bitmap(np.ascontiguousarray(bmp[::-1])).write(str(tmp_path / name))
    med, _ = errors(render(tmp_path / "scene.xml"), ggx, mask)
    assert med > 0.05, med

"""Writes fichet2021-bispectral.exr, the bispectral image `cargo test -p lightrig-imaging`
reads back (imaging/tests/spectral_exr.rs), with the Academy Software Foundation's OpenEXR
Python bindings (`pip install OpenEXR`), in the layout of Fichet, Pacanowski and Wilkie (2021)
as their SEXR library names channels: `T.<lambda>nm` for the diagonal and
`T.<lambda_in>nm.<lambda_out>nm` for reradiation, six decimals after a comma.

Values: pixel (x, y) of a 4 x 3 image, channel k (in the order listed below) holds
0.001 * (1 + k) * (1 + x + 4 * y).
"""
import numpy as np
import OpenEXR

W, H = 4, 3
diagonal = [400.0, 420.0, 440.5]
reradiation = [(400.0, 440.5), (400.0, 520.0), (420.0, 520.0)]


def name(nm):
    return f"{nm:.6f}".replace(".", ",") + "nm"


channels = {}
k = 0
pixel = 1 + np.arange(W)[None, :] + 4 * np.arange(H)[:, None]
for nm in diagonal:
    channels[f"T.{name(nm)}"] = (0.001 * (1 + k) * pixel).astype(np.float32)
    k += 1
for i, o in reradiation:
    channels[f"T.{name(i)}.{name(o)}"] = (0.001 * (1 + k) * pixel).astype(np.float32)
    k += 1
header = {
    "compression": OpenEXR.ZIP_COMPRESSION,
    "type": OpenEXR.scanlineimage,
    "spectralLayoutVersion": "1.0",
}
with OpenEXR.File(header, channels) as f:
    f.write("fichet2021-bispectral.exr")

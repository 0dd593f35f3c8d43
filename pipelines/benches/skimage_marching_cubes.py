#!/usr/bin/env python3
"""Time scikit-image's marching cubes on the volume that
`cargo bench -p lightrig-pipelines --bench marching_cubes` writes when LIGHTRIG_MC_DUMP is set
(256^3 float32, x fastest; a bumpy sphere's signed distance, surface at 0).

    LIGHTRIG_MC_DUMP=/tmp/lightrig-mc cargo bench -p lightrig-pipelines --bench marching_cubes
    pip install --user scikit-image
    python3 pipelines/benches/skimage_marching_cubes.py /tmp/lightrig-mc

Prints the best of 10 runs (after a warm-up) in voxels per second, with the mesh size.
scikit-image's marching cubes is single-threaded.
"""
import sys
import time

import numpy as np
import skimage
from skimage.measure import marching_cubes


def main():
    d = sys.argv[1] if len(sys.argv) > 1 else "/tmp/lightrig-mc"
    runs = int(sys.argv[2]) if len(sys.argv) > 2 else 10
    nx, ny, nz = (int(v) for v in open(f"{d}/dims.txt").read().split())
    vol = np.fromfile(f"{d}/volume.f32", dtype="<f4").reshape(nz, ny, nx)
    verts, faces, _, _ = marching_cubes(vol, level=0.0)  # warm-up
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        marching_cubes(vol, level=0.0)
        times.append(time.perf_counter() - t0)
    best = min(times)
    print(f"scikit-image {skimage.__version__} marching_cubes (lewiner): {len(verts)} vertices, "
          f"{len(faces)} triangles; best of {runs} {best * 1e3:.1f} ms, "
          f"median {np.median(times) * 1e3:.1f} ms, {nx * ny * nz / best / 1e6:.0f} Mvoxel/s")


if __name__ == "__main__":
    main()

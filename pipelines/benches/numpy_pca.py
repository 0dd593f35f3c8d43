#!/usr/bin/env python3
"""Time NumPy's SVD on the matrix that `cargo bench -p lightrig-pipelines --bench brrdf_pca`
writes when LIGHTRIG_PCA_DUMP is set (32768 x 170 float64, row-major): the mean removed, then
`np.linalg.svd(F, full_matrices=False)`, as thesis section 4.5 computes its PCA.

    LIGHTRIG_PCA_DUMP=/tmp/lightrig-pca cargo bench -p lightrig-pipelines --bench brrdf_pca
    python3 pipelines/benches/numpy_pca.py /tmp/lightrig-pca

Prints the best of 5 runs (after a warm-up) and NumPy's BLAS.
"""
import sys
import time

import numpy as np


def main():
    d = sys.argv[1] if len(sys.argv) > 1 else "/tmp/lightrig-pca"
    runs = int(sys.argv[2]) if len(sys.argv) > 2 else 5
    rows, cols = (int(v) for v in open(f"{d}/shape.txt").read().split())
    f = np.fromfile(f"{d}/f.f64", dtype="<f8").reshape(rows, cols)

    def pca():
        c = f - f.mean(axis=0)
        return np.linalg.svd(c, full_matrices=False)

    u, s, vt = pca()  # warm-up
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        pca()
        times.append(time.perf_counter() - t0)
    energy = s**2
    blas = np.show_config(mode="dicts").get("Build Dependencies", {}).get("blas", {}).get("name", "?")
    print(f"NumPy {np.__version__} ({blas}) SVD {rows}x{cols}: best of {runs} {min(times) * 1e3:.1f} ms, "
          f"median {np.median(times) * 1e3:.1f} ms ({energy[:6].sum() / energy.sum():.4f} of the energy in 6)")


if __name__ == "__main__":
    main()

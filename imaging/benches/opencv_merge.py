#!/usr/bin/env python3
"""Time OpenCV's MergeDebevec on the stack that `cargo bench -p lightrig-imaging --bench hdr`
writes when LIGHTRIG_HDR_DUMP is set (16 exposures, 1024x768 RGB, 8-bit, gamma-2.2 response).

    LIGHTRIG_HDR_DUMP=/tmp/lightrig-hdr cargo bench -p lightrig-imaging --bench hdr
    pip install opencv-python-headless numpy
    python3 imaging/benches/opencv_merge.py /tmp/lightrig-hdr

Prints input megapixels per second (width*height*exposures / time per merge).
"""
import sys
import time

import cv2
import numpy as np


def main():
    d = sys.argv[1] if len(sys.argv) > 1 else "/tmp/lightrig-hdr"
    threads = int(sys.argv[2]) if len(sys.argv) > 2 else 2
    cv2.setNumThreads(threads)
    w, h, p = (int(v) for v in open(f"{d}/size.txt").read().split())
    images = [np.fromfile(f"{d}/stack_{j:02}.rgb", dtype=np.uint8).reshape(h, w, 3) for j in range(p)]
    times = np.array([float(t) for t in open(f"{d}/times.txt").read().split()], dtype=np.float32)
    response = np.fromfile(f"{d}/response.f32", dtype="<f4").reshape(256, 1, 3)
    merge = cv2.createMergeDebevec()
    merge.process(images, times, response)  # warm-up
    runs = []
    for _ in range(10):
        t0 = time.perf_counter()
        merge.process(images, times, response)
        runs.append(time.perf_counter() - t0)
    dt = float(np.median(runs))
    print(f"OpenCV {cv2.__version__} MergeDebevec, {cv2.getNumThreads()} threads: "
          f"{dt * 1e3:.1f} ms per merge (median of 10), {w * h * p / dt / 1e6:.0f} input Mpx/s")


if __name__ == "__main__":
    main()

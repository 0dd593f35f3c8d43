#!/usr/bin/env python3
"""OpenCV's chessboard detector on the boards `cargo run --release -p lightrig-imaging --example
chessboard_grid -- DIR` writes (PGM images and their true corners), beside lightrig's results
(DIR/lightrig.csv): how many each finds, and how many with every corner within 0.3 px.

    cargo run --release -p lightrig-imaging --example chessboard_grid -- /tmp/boards
    pip install opencv-python-headless numpy
    python3 imaging/benches/opencv_chessboards.py /tmp/boards 5      # cornerSubPix winSize (5, 5)
"""
import glob
import os
import sys

import cv2
import numpy as np


def main():
    d = sys.argv[1] if len(sys.argv) > 1 else "/tmp/boards"
    win = int(sys.argv[2]) if len(sys.argv) > 2 else 5
    # lightrig's results, when the example wrote them (a test's dump has none).
    ours = None
    if os.path.exists(f"{d}/lightrig.csv"):
        ours = {}
        for line in open(f"{d}/lightrig.csv").read().split("\n")[1:]:
            if line:
                name, found, mx, _ = line.split(",")
                ours[name] = (found == "1", float(mx) if mx else float("nan"))
    n = cv_found = cv_close = lr_found = lr_close = 0
    for f in sorted(glob.glob(f"{d}/*.pgm")):
        name = os.path.basename(f)[:-4]
        if not os.path.exists(f[:-4] + ".truth") or (ours is not None and name not in ours):
            continue  # not one of this run's boards
        img = cv2.imread(f, cv2.IMREAD_GRAYSCALE)
        truth = np.loadtxt(f[:-4] + ".truth")
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH + cv2.CALIB_CB_NORMALIZE_IMAGE
        ok, c = cv2.findChessboardCorners(img, (9, 6), flags)
        n += 1
        if ok:
            crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001)
            c = cv2.cornerSubPix(img, c, (win, win), (-1, -1), crit).reshape(-1, 2)
            # OpenCV may start at the other end of the board.
            err = min(np.hypot(*(c - truth).T).max(), np.hypot(*(c[::-1] - truth).T).max())
            cv_found += 1
            cv_close += err < 0.3
        found, mx = (ours or {}).get(name, (False, float("nan")))
        lr_found += found
        lr_close += found and mx < 0.3
    line = f"{n} boards; OpenCV {cv2.__version__} (cornerSubPix {win}x{win}): found {cv_found}, {cv_close} within 0.3 px"
    if ours is not None:
        line += f"; lightrig: found {lr_found}, {lr_close} within 0.3 px"
    print(line)


if __name__ == "__main__":
    main()

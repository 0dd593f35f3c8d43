"""Reading a session's frames from Python beside the Rust reader it wraps, in the same run,
alternating round by round (docs/benchmarks.md):

    python python/benches/read_frames.py SESSION [ROUNDS]

The Rust side is `cargo bench -p lightrig-host --bench read_frames` (built first, outside the
timing); the Python side iterates `lightrig.Session(SESSION).frames()` and touches each frame's
pixels, as an analysis loop does.
"""

import pathlib
import subprocess
import sys
import time

import lightrig

ROOT = pathlib.Path(__file__).resolve().parents[2]


def rust_bench():
    """The bench binary's path, built in the bench profile."""
    out = subprocess.run(
        ["cargo", "bench", "-p", "lightrig-host", "--bench", "read_frames", "--no-run", "--message-format", "json"],
        cwd=ROOT, capture_output=True, text=True, check=True,
    ).stdout
    import json

    for line in out.splitlines():
        m = json.loads(line)
        if m.get("reason") == "compiler-artifact" and m["target"]["name"] == "read_frames" and m.get("executable"):
            return m["executable"]
    raise SystemExit("no read_frames bench binary")


def python_round(session):
    t0 = time.perf_counter()
    s = lightrig.Session(session)
    frames = nbytes = 0
    for f in s.frames():
        p = f.pixels
        frames += 1
        nbytes += p.nbytes
    sec = time.perf_counter() - t0
    return frames, sec, nbytes


def main():
    session = sys.argv[1]
    rounds = int(sys.argv[2]) if len(sys.argv) > 2 else 3
    exe = rust_bench()
    rust, py = [], []
    for _ in range(rounds):
        line = subprocess.run([exe, session, "1"], capture_output=True, text=True, check=True).stdout.strip()
        print(line)
        rust.append(float(line.split()[3]))
        frames, sec, nbytes = python_round(session)
        print(f"python {frames} frames  {sec:.3f} s  {frames / sec:.0f} frames/s  {nbytes / sec / 1e6:.1f} MB/s")
        py.append(sec)
    # The first round reads from a cold page cache: left out when there are more.
    warm = slice(1, None) if rounds > 1 else slice(None)
    r, p = sorted(rust[warm])[len(rust[warm]) // 2], sorted(py[warm])[len(py[warm]) // 2]
    print(f"median of the warm rounds: rust {r:.3f} s, python {p:.3f} s: python takes {100 * (p / r - 1):+.1f} %")


if __name__ == "__main__":
    main()

"""Shared fixtures: the quick demos' sessions, and the `lightrig` binary for comparisons.

The LLS demo is always run here, through `lightrig.demo` (what it returned is the `lls_run`
fixture). The other rigs' sessions come from `LIGHTRIG_DEMOS` (a directory with `<rig>/` from
their quick demos; CI points it at the outputs its Rust demo tests kept, as
`LIGHTRIG_KEEP_DEMOS` asks them to) or, where that has none, from `lightrig.demo(rig,
quick=True)` run here once per test session.
"""

import os
import pathlib
import shutil
import subprocess

import pytest

import lightrig

ROOT = pathlib.Path(__file__).resolve().parents[2]


def lightrig_binary():
    """The `lightrig` command: `LIGHTRIG_BIN`, else the workspace's debug or release build."""
    env = os.environ.get("LIGHTRIG_BIN")
    if env:
        return env
    for profile in ("debug", "release"):
        p = ROOT / "target" / profile / "lightrig"
        if p.exists():
            return str(p)
    found = shutil.which("lightrig")
    if found:
        return found
    pytest.fail("no lightrig binary: build it (cargo build --bin lightrig) or set LIGHTRIG_BIN")


def run_cli(*args):
    """Runs `lightrig ARGS…`; returns (exit code, stdout, stderr)."""
    p = subprocess.run([lightrig_binary(), *map(str, args)], capture_output=True, text=True)
    return p.returncode, p.stdout, p.stderr


class Demos:
    def __init__(self, scratch):
        self.scratch = scratch
        self.kept = os.environ.get("LIGHTRIG_DEMOS")
        self.dirs = {}
        self.runs = {}

    def run(self, rig):
        """`lightrig.demo(rig, quick=True)` here, once."""
        if rig not in self.runs:
            self.runs[rig] = lightrig.demo(rig, quick=True, out=self.scratch)
            self.dirs[rig] = pathlib.Path(self.runs[rig]["dir"])
        return self.runs[rig]

    def __call__(self, rig):
        if rig not in self.dirs:
            kept = pathlib.Path(self.kept) / rig if self.kept and rig != "lls" else None
            if kept is not None and (kept / "report.md").exists():
                self.dirs[rig] = kept
            else:
                self.run(rig)
        return self.dirs[rig]


@pytest.fixture(scope="session")
def demos(tmp_path_factory):
    """`demos(rig)`: the directory of that rig's quick demo (`session/`, `fit/`, `report.md`…)."""
    return Demos(tmp_path_factory.mktemp("demos"))


@pytest.fixture(scope="session")
def lls_run(demos):
    return demos.run("lls")


@pytest.fixture(scope="session")
def lls_dir(lls_run):
    return pathlib.Path(lls_run["dir"])


@pytest.fixture(scope="session")
def lls_session(lls_dir):
    return lls_dir / "session"

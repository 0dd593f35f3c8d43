"""lightrig.demo: the virtual rig's demo as `lightrig demo` runs it."""

import pathlib
import subprocess
import sys
import textwrap

import pytest

import lightrig
from conftest import run_cli
from test_session import read_journal


def test_the_lls_demo_returns_its_report_and_session(lls_run):
    d = pathlib.Path(lls_run["dir"])
    assert lls_run["method"] == "lls" and d.name == "lls"
    assert pathlib.Path(lls_run["report_path"]) == d / "report.md"
    assert lls_run["report"] == (d / "report.md").read_text() and "ground truth" in lls_run["report"].lower()
    assert lls_run["missed"] == []
    assert lls_run["sessions"] == [str(d / "session")]
    s = lightrig.Session(lls_run["sessions"][0])
    assert s.done and len(s) > 0


def test_an_unknown_method_raises_the_command_s_message(tmp_path):
    code, _, err = run_cli("demo", "nope", "--out", tmp_path)
    assert code == 2
    with pytest.raises(lightrig.DemoError) as e:
        lightrig.demo("nope", out=tmp_path)
    assert err.strip() == f"error: {e.value}"


def test_ctrl_c_stops_a_demo_s_acquisition_with_an_emergency_stop(tmp_path):
    # A timer thread sends SIGINT once the virtual camera has written frames; the acquisition
    # ends at once (the journal abandons its step, no report is written) and KeyboardInterrupt
    # is what Python sees.
    script = textwrap.dedent(
        f"""
        import os, pathlib, signal, threading, time, lightrig
        journal = pathlib.Path({str(tmp_path)!r}) / "lls" / "session" / "journal.jsonl"
        def interrupt():
            while not (journal.exists() and journal.read_text().count('"type":"Frame"') >= 5):
                time.sleep(0.02)
            print("interrupting", flush=True)
            os.kill(os.getpid(), signal.SIGINT)
        threading.Thread(target=interrupt, daemon=True).start()
        lightrig.demo("lls", quick=True, out={str(tmp_path)!r})
        print("finished", flush=True)
        """
    )
    p = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert p.stdout.splitlines()[-1] == "interrupting" and "finished" not in p.stdout, p.stdout + p.stderr
    assert p.returncode == -2 and p.stderr.rstrip().endswith("KeyboardInterrupt"), p.stderr
    d = tmp_path / "lls"
    assert not (d / "report.md").exists()
    s = lightrig.Session(d / "session")
    assert not s.done and sum(st["done"] for st in s.steps()) < len(s.steps())
    # Every step begun ended: done, or (the one the stop cut short) abandoned for the stop.
    records = read_journal(d / "session")
    ends = {(r["step"], r["attempt"]): r for r in records if r["type"] in ("StepDone", "StepAbandoned")}
    begun = [(r["step"], r["attempt"]) for r in records if r["type"] == "StepStarted"]
    assert all(b in ends for b in begun), (begun, ends)
    abandoned = [r for r in ends.values() if r["type"] == "StepAbandoned"]
    assert len(abandoned) <= 1 and all("EmergencyStop" in r["reason"] for r in abandoned), abandoned

"""lightrig.demo: the virtual rig's demo as `lightrig demo` runs it."""

import pathlib

import pytest

import lightrig
from conftest import run_cli


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

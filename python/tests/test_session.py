"""lightrig.Session against the session format read with the standard library alone (the reader
of docs/session-format.md §10) and the frames decoded by another PNG reader (pypng)."""

import json
import pathlib
import shutil
import zlib

import numpy as np
import png  # pypng: a PNG decoder that is not lightrig's
import pytest

import lightrig

HEX = set(b"0123456789abcdef")


def read_journal(session):
    """The committed records, in order; stops at the first torn or damaged line (§10)."""
    records = []
    with open(pathlib.Path(session) / "journal.jsonl", "rb") as f:
        for line in f:
            if not line.endswith(b"\n") or len(line) < 10 or line[8:9] != b"\t":
                break
            crc, payload = line[:8], line[9:-1]
            if not set(crc) <= HEX or int(crc, 16) != zlib.crc32(payload):
                break
            records.append(json.loads(payload))
    return records


def done_frames(session):
    records = read_journal(session)
    done = {r["step"]: r["attempt"] for r in records if r["type"] == "StepDone"}
    triggers = {}
    for r in records:
        if r["type"] == "Event" and "Trigger" in r["event"]:
            t = r["event"]["Trigger"]
            triggers[(t["sequence"], t["item"])] = t
    frames = [r for r in records if r["type"] == "Frame" and done.get(r["step"]) == r["attempt"]]
    return frames, triggers


def test_manifest_rig_and_steps(lls_session):
    s = lightrig.Session(lls_session)
    manifest = json.loads((lls_session / "manifest.json").read_text())
    assert s.manifest == manifest
    assert s.rig_text == manifest["rig"]
    assert s.rig["rig"]["name"]
    assert s.method == manifest["plan"]["extra"]["method"] == "linear-light-source"
    assert s.tick_hz == manifest["device"]["tick_hz"]
    assert s.done
    steps = s.steps()
    assert [st["id"] for st in steps] == [st["id"] for st in manifest["plan"]["steps"]]
    frames, _ = done_frames(lls_session)
    for st, planned in zip(steps, manifest["plan"]["steps"]):
        assert st["name"] == planned["name"] and st["done"] and st["attempt"] >= 1
        assert st["expected"] == {t["camera"]: t["count"] for t in planned["triggers"]}
        for cam, n in st["frames"].items():
            assert n == sum(1 for f in frames if f["step"] == st["id"] and f["camera"] == cam)
    assert len(s) == len(frames)
    assert s.missing() == [] and s.extras() == []
    n = len(manifest["plan"]["steps"])
    name = json.dumps(s.rig["rig"]["name"])  # Rust's {:?} of a plain string
    assert repr(s) == f"Session('{lls_session}', rig={name}, {n} of {n} steps done, complete)"


def test_frames_are_the_journal_s_with_their_triggers(lls_session):
    s = lightrig.Session(lls_session)
    frames, triggers = done_frames(lls_session)
    step = s.steps()[0]["id"]
    ours = list(s.frames(step=step))
    theirs = [f for f in frames if f["step"] == step]
    assert len(ours) == len(theirs) > 0
    for f, r in zip(ours, theirs):
        assert f.record == r
        assert (f.step, f.camera, f.frame, f.tick, f.file) == (r["step"], r["camera"], r["frame"], r["tick"], r["file"])
        t = triggers[(r["sequence"], r["item"])]
        assert f.trigger == t and f.trigger["snapshot"]["axes"] == t["snapshot"]["axes"]
        assert f.exposure_s == pytest.approx(t["width"] / s.tick_hz, rel=1e-12)
    # Every frame of the session, in plan order, once.
    every = [(f.step, f.camera, f.frame) for f in s.frames()]
    order = {st["id"]: k for k, st in enumerate(s.steps())}
    assert every == sorted(((r["step"], r["camera"], r["frame"]) for r in frames), key=lambda x: (order[x[0]], x[1], x[2]))
    assert len(list(s.frames(step=[step], camera=99))) == 0


def test_pixels_match_an_independent_png_decoder(lls_session):
    s = lightrig.Session(lls_session)
    for k, f in enumerate(s.frames()):
        if k % 37:
            continue
        w, h, rows, info = png.Reader(filename=str(lls_session / f.file)).read_flat()
        planes = info["planes"]
        ref = np.asarray(rows, dtype=np.float64).reshape(h, w, planes) / (2 ** info["bitdepth"] - 1)
        a = f.pixels
        assert f.bits == info["bitdepth"]
        assert a.dtype == np.float32 and a.shape == ((h, w) if planes == 1 else (h, w, planes))
        np.testing.assert_allclose(a.reshape(h, w, planes), ref, rtol=0, atol=1e-7)


def test_a_frame_s_array_is_one_buffer_not_copied(lls_session):
    s = lightrig.Session(lls_session)
    f = next(iter(s.frames()))
    a, b = f.pixels, f.pixels
    assert a is b
    assert a.flags.c_contiguous and a.flags.writeable and a.flags.aligned
    # The Rust buffer moved into NumPy, reshaped as a view: no copy of the pixels.
    assert not a.flags.owndata
    base = a.base
    assert isinstance(base, np.ndarray) and base.ndim == 1 and base.size == a.size
    assert np.shares_memory(a, base) and not base.flags.owndata  # base: the Rust Vec's memory


def test_an_unknown_step_is_refused_with_the_plan_s_steps(lls_session):
    s = lightrig.Session(lls_session)
    with pytest.raises(lightrig.SessionError, match=r"the plan has no step 999999 \(its steps: "):
        s.frames(step=999999)
    with pytest.raises(lightrig.SessionError, match="the plan has no step 999999"):
        s.records(999999)


def test_records_of_a_step(lls_session):
    s = lightrig.Session(lls_session)
    step = s.steps()[1]["id"]
    r = s.records(step)
    frames, triggers = done_frames(lls_session)
    assert r["frames"] == [f for f in frames if f["step"] == step]
    assert r["missing"] == [] and r["extra"] == []
    assert {(t["sequence"], t["item"]) for t in r["triggers"]} >= {(f["sequence"], f["item"]) for f in r["frames"]}


def copy_session(src, dst):
    shutil.copytree(src, dst)
    return dst


def test_a_torn_last_line_is_ignored_and_its_step_is_not_done(lls_session, tmp_path):
    d = copy_session(lls_session, tmp_path / "torn")
    journal = d / "journal.jsonl"
    lines = journal.read_bytes().splitlines(keepends=True)
    # Cut the journal inside the last step: its StepDone and SessionDone are gone, the last
    # line is torn halfway.
    last_step = lightrig.Session(lls_session).steps()[-1]["id"]
    cut = max(i for i, l in enumerate(lines) if b'"type":"StepStarted"' in l and f'"step":{last_step},'.encode() in l)
    journal.write_bytes(b"".join(lines[: cut + 3]) + lines[cut + 3][:20])
    s = lightrig.Session(d)
    assert not s.done
    steps = s.steps()
    assert not steps[-1]["done"] and steps[-1]["attempt"] is None and all(st["done"] for st in steps[:-1])
    assert all(f.step != last_step for f in s.frames())


def test_a_damaged_line_raises_naming_the_file_and_line(lls_session, tmp_path):
    d = copy_session(lls_session, tmp_path / "damaged")
    journal = d / "journal.jsonl"
    lines = journal.read_bytes().splitlines(keepends=True)
    k = len(lines) // 2
    lines[k] = lines[k][:12] + (b"X" if lines[k][12:13] != b"X" else b"Y") + lines[k][13:]
    journal.write_bytes(b"".join(lines))
    with pytest.raises(lightrig.SessionError) as e:
        lightrig.Session(d)
    assert "journal.jsonl" in str(e.value) and f"line {k + 1}" in str(e.value)


def test_a_frame_file_changed_on_disk_is_named(lls_session, tmp_path):
    d = copy_session(lls_session, tmp_path / "changed")
    s = lightrig.Session(d)
    first = next(iter(s.frames()))
    p = d / first.file
    data = bytearray(p.read_bytes())
    data[-20] ^= 0xFF
    p.write_bytes(bytes(data))
    with pytest.raises(lightrig.SessionError) as e:
        next(iter(s.frames()))
    assert first.file in str(e.value) and "CRC-32" in str(e.value)


def test_not_a_session(tmp_path):
    with pytest.raises(lightrig.SessionError) as e:
        lightrig.Session(tmp_path)
    assert str(tmp_path) in str(e.value)


def rewrite(journal, edit):
    """Rewrites the journal's records through `edit(records) -> records`, each line's CRC-32
    computed here (docs/session-format.md §3)."""
    lines = journal.read_bytes().splitlines()
    records = [json.loads(l[9:]) for l in lines]
    out = []
    for r in edit(records):
        payload = json.dumps(r, separators=(",", ":")).encode()
        out.append(b"%08x\t%s\n" % (zlib.crc32(payload), payload))
    journal.write_bytes(b"".join(out))


def test_missing_and_extra_frames_are_visible(lls_session, tmp_path):
    d = copy_session(lls_session, tmp_path / "missing")
    longest = max(lightrig.Session(d).steps(), key=lambda st: sum(st["expected"].values()))
    step = longest["id"]

    def edit(records):
        out, done = [], False
        for r in records:
            if not done and r["type"] == "Frame" and r["step"] == step and r["frame"] == 3:
                done = True
                out.append({"type": "FrameMissing", **{k: r[k] for k in ("step", "attempt", "camera", "frame", "sequence", "item", "tick", "trigger_us")},
                            "reason": "no frame arrived within the wait"})
                out.append({"type": "FrameExtra", **{k: r[k] for k in ("step", "attempt", "camera", "arrived_us", "file", "bytes", "crc32")},
                            "frame": 90000, "reason": "NoTrigger"})
                continue
            if r["type"] == "StepDone" and r["step"] == step:
                r = dict(r, frames=r["frames"] - 1, missing=r["missing"] + 1, extra=r["extra"] + 1)
            out.append(r)
        assert done
        return out

    rewrite(d / "journal.jsonl", edit)
    s = lightrig.Session(d)
    [m] = s.missing()
    assert (m["type"], m["step"], m["frame"], m["reason"]) == ("FrameMissing", step, 3, "no frame arrived within the wait")
    [x] = s.extras()
    assert (x["type"], x["frame"], x["reason"]) == ("FrameExtra", 90000, "NoTrigger")
    st = next(st for st in s.steps() if st["id"] == step)
    cam = next(iter(st["expected"]))
    assert st["frames"][cam] == st["expected"][cam] - 1
    assert [f.frame for f in s.frames(step=step) if f.camera == cam].count(3) == 0
    r = s.records(step)
    assert [m["frame"] for m in r["missing"]] == [3] and [x["frame"] for x in r["extra"]] == [90000]

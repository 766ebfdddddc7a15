"""The stage records (:mod:`plantsplat.stages`): when a stage runs again, when it is skipped, and that a
failed, interrupted or out-of-date stage is never built on."""

from __future__ import annotations

import json
import shutil

import pytest

from plantsplat.errors import PlantsplatError
from plantsplat.stages import read_record, require_ok, run_stage
from plantsplat.workspace import Workspace


@pytest.fixture()
def ws(tmp_path):
    ws = Workspace(tmp_path / "ws")
    ws.root.mkdir()
    (ws.root / "in.txt").write_text("input")
    return ws


def _stage(ws, calls, config=None, fail=None, **kw):
    """A stage that copies in.txt to out.txt (upper-cased), recording each run and its resume flag."""

    def work(resume):
        calls.append(resume)
        if fail is not None:
            raise fail
        (ws.root / "out.txt").write_text((ws.root / "in.txt").read_text().upper())
        return {"n": 1, "skip": [1, 2]}

    return run_stage(ws, "copy", config or {"a": 1}, [ws.root / "in.txt"], [ws.root / "out.txt"], work, **kw)


def test_runs_once_then_is_up_to_date(ws):
    calls = []
    assert _stage(ws, calls) == {"n": 1, "skip": [1, 2]}
    again = _stage(ws, calls)
    assert calls == [False] and again["up_to_date"] and again["n"] == 1
    rec = read_record(ws, "copy")
    assert rec["status"] == "ok" and rec["config"] == {"a": 1} and "in.txt" in rec["inputs"]
    _stage(ws, calls, force=True)
    assert calls == [False, False]


@pytest.mark.parametrize("change", ["option", "input", "output_damaged", "output_deleted"])
def test_runs_again_when_anything_it_depends_on_changed(ws, change):
    calls = []
    _stage(ws, calls)
    config = None
    if change == "option":
        config = {"a": 2}
    elif change == "input":
        (ws.root / "in.txt").write_text("another input")
    elif change == "output_damaged":
        (ws.root / "out.txt").write_text("IN")
    else:
        (ws.root / "out.txt").unlink()
    _stage(ws, calls, config=config)
    assert calls == [False, False]
    assert (ws.root / "out.txt").read_text() == (ws.root / "in.txt").read_text().upper()


def test_a_failed_stage_runs_again_and_is_not_built_on(ws):
    calls = []
    _stage(ws, calls)
    with pytest.raises(PlantsplatError, match="no luck"):
        _stage(ws, calls, config={"a": 2}, fail=PlantsplatError("no luck"))
    rec = read_record(ws, "copy")
    assert rec["status"] == "failed" and rec["reason"] == "no luck"
    with pytest.raises(PlantsplatError, match=r"the copy stage failed: no luck; fix that and run `plantsplat copy"):
        require_ok(ws, "copy")
    # the old outputs are still there and match their fingerprints, but the record says failed: it runs again
    _stage(ws, calls)
    assert calls == [False, False, False] and read_record(ws, "copy")["status"] == "ok"
    require_ok(ws, "copy")


def test_an_interrupted_stage_resumes_with_the_same_options_only(ws):
    calls = []
    with pytest.raises(KeyboardInterrupt):
        _stage(ws, calls, fail=KeyboardInterrupt())
    assert read_record(ws, "copy")["status"] == "running"
    with pytest.raises(PlantsplatError, match="the copy stage running"):
        require_ok(ws, "copy")
    with pytest.raises(KeyboardInterrupt):
        _stage(ws, calls, fail=KeyboardInterrupt())
    _stage(ws, calls, config={"a": 2})  # other options: nothing of the interrupted run is reused
    assert calls == [False, True, False]


def _chain(ws, name, src, dst):
    """A stage ``name`` that writes ``dst`` from ``src`` (upper-cased)."""
    def work(resume):
        (ws.root / dst).write_text((ws.root / src).read_text().upper())
        return {}

    return run_stage(ws, name, {}, [ws.root / src], [ws.root / dst], work)


def test_a_stage_whose_input_an_earlier_stage_wrote_again_is_not_built_on(ws, tmp_path):
    """`train --force` then `traits`: the export in between is out of date, and the traits are not measured on it."""
    _chain(ws, "make", "in.txt", "a.txt")
    _chain(ws, "use", "a.txt", "b.txt")
    require_ok(ws, "use")
    (ws.root / "in.txt").write_text("new input")
    _chain(ws, "make", "in.txt", "a.txt")  # the earlier stage runs again and writes a.txt anew
    with pytest.raises(PlantsplatError, match=r"the use stage is out of date: the make stage wrote a.txt again after "
                                              r"it ran; run `plantsplat use .*` again"):
        require_ok(ws, "use")
    _chain(ws, "use", "a.txt", "b.txt")
    require_ok(ws, "use")
    # a file changed by hand is no stage's writing: the stage reading it runs again, and is then up to date
    (ws.root / "a.txt").write_text("BY HAND")
    _chain(ws, "use", "a.txt", "b.txt")
    require_ok(ws, "use")
    # a copied workspace (every file's time new) keeps its records' agreement
    copy = Workspace(tmp_path / "copy")
    shutil.copytree(ws.root, copy.root, copy_function=shutil.copy)
    require_ok(copy, "use")


def test_a_stage_built_on_an_out_of_date_stage_is_not_built_on(ws):
    """`segment --force` then `traits`: the export is up to date with its model, but the model was trained on the
    old masks; the command names the first stage to run again."""
    _chain(ws, "make", "in.txt", "a.txt")
    _chain(ws, "mid", "a.txt", "b.txt")
    _chain(ws, "last", "b.txt", "c.txt")
    require_ok(ws, "last")
    (ws.root / "in.txt").write_text("new input")
    _chain(ws, "make", "in.txt", "a.txt")
    with pytest.raises(PlantsplatError, match=r"the last stage is out of date: it was built on the mid stage, and the "
                                              r"make stage wrote a.txt again after that ran; run `plantsplat mid .*` "
                                              r"and the stages after it again"):
        require_ok(ws, "last")
    _chain(ws, "mid", "a.txt", "b.txt")
    with pytest.raises(PlantsplatError, match=r"the last stage is out of date: the mid stage wrote b.txt again"):
        require_ok(ws, "last")
    _chain(ws, "last", "b.txt", "c.txt")
    require_ok(ws, "last")


def test_records_made_before_their_finishing_time_was_kept_are_compared_by_their_time(ws):
    """A workspace made by an earlier plantsplat, whose ok records hold only the time they were written."""
    _chain(ws, "make", "in.txt", "a.txt")
    _chain(ws, "use", "a.txt", "b.txt")
    for stage, when in (("make", "2026-11-01T10:00:00+0000"), ("use", "2026-11-01T10:05:00+0000")):
        path = ws.root / ".plantsplat" / "stages" / f"{stage}.json"
        rec = json.loads(path.read_text())
        rec.pop("finished")
        path.write_text(json.dumps({**rec, "time": when}))
    require_ok(ws, "use")
    (ws.root / "in.txt").write_text("new input")
    _chain(ws, "make", "in.txt", "a.txt")  # runs now, after 10:05
    with pytest.raises(PlantsplatError, match="the use stage is out of date"):
        require_ok(ws, "use")


def test_no_record_is_left_to_the_stage_own_checks(ws):
    require_ok(ws, "frames")  # images put there by hand: the next stage checks its inputs itself
    (ws.root / ".plantsplat" / "stages").mkdir(parents=True)
    (ws.root / ".plantsplat" / "stages" / "copy.json").write_text("{truncated")
    calls = []
    _stage(ws, calls)  # an unreadable record means: run again
    assert calls == [False]


def test_a_full_disk_names_the_write_that_failed_and_the_stage_resumes(ws, monkeypatch):
    """Issue 42 #11: when the disk fills up during a stage, the error names the stage's file whose write failed (not
    the record or run.json, whose writes then fail too); the record left `running` is taken as interrupted."""
    import errno
    import tempfile

    from plantsplat.io import os_error_message

    real_mkstemp = tempfile.mkstemp

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    def fill_the_disk():
        monkeypatch.setattr(tempfile, "mkstemp", full)
        raise PlantsplatError(os_error_message(OSError(errno.ENOSPC, "No space left"), ws.root / "train" / "model.pt"))

    calls = []

    def work(resume):
        calls.append(resume)
        fill_the_disk()

    with pytest.raises(PlantsplatError, match=r"train/model.pt: the disk is full"):
        run_stage(ws, "copy", {"a": 1}, [ws.root / "in.txt"], [ws.root / "out.txt"], work)
    assert read_record(ws, "copy")["status"] == "running"
    monkeypatch.setattr(tempfile, "mkstemp", real_mkstemp)  # space freed
    _stage(ws, calls)
    assert calls == [False, True] and read_record(ws, "copy")["status"] == "ok"


def test_a_full_disk_during_run_names_the_stage_file_not_run_json(tmp_path, monkeypatch):
    import errno
    import tempfile

    from plantsplat import pipeline
    from plantsplat.io import os_error_message

    video = tmp_path / "video.mp4"
    video.write_bytes(b"\0" * 64)

    def frames_fill_the_disk(ws, source, cfg, force=False):
        monkeypatch.setattr(tempfile, "mkstemp", lambda *a, **k: (_ for _ in ()).throw(OSError(errno.ENOSPC, "full")))
        raise PlantsplatError(os_error_message(OSError(errno.ENOSPC, "full"), ws.images_dir / "frame_00003.png"))

    monkeypatch.setattr(pipeline, "frames_stage", frames_fill_the_disk)
    with pytest.raises(PlantsplatError, match=r"frame_00003.png: the disk is full"):
        pipeline.run_pipeline(video, tmp_path / "ws", pipeline.RunConfig(report=False))

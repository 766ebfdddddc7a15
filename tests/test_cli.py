"""The command line against hostile but realistic use (issue 42): bad option values and paths refused at the
start with one line and exit code 2, a capture folder's own masks never overwritten, typos said in one line,
spreadsheet-safe CSVs, `batch --no-report`."""

from __future__ import annotations

import shutil

import pytest

from plantsplat.cli import main
from plantsplat.stages import record_path
from plantsplat.workspace import Workspace


def _one_error_line(err: str, *words: str) -> None:
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:"), err
    for w in words:
        assert w in lines[0], (w, lines[0])


@pytest.fixture()
def finished_records(tmp_path):
    """A workspace whose every stage record says ok (what a finished run leaves): ``(ws, {path: bytes})``."""
    ws = Workspace(tmp_path / "ws")
    records = {}
    for stage in ("frames", "poses", "segment", "train", "export", "traits"):
        p = record_path(ws, stage)
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text('{"version": 1, "stage": "%s", "status": "ok", "config": {}}\n' % stage)
        records[p] = p.read_bytes()
    return ws, records


@pytest.mark.parametrize("args, option", [
    (["poses", "{ws}", "--cube-size", "0"], "--cube-size 0"),
    (["poses", "{ws}", "--cube-size", "-5"], "--cube-size -5"),
    (["poses", "{ws}", "--cube-size", "nan"], "--cube-size nan"),
    (["poses", "{ws}", "--marker-size", "12"], "--marker-size 12"),
    (["export", "{ws}", "--min-opacity", "2"], "--min-opacity 2"),
    (["frames", "{video}", "--out", "{ws}", "--blur-ratio", "nan"], "--blur-ratio nan"),
    (["run", "{video}", "--out", "{ws}", "--poses.cube-size", "0"], "--poses.cube-size 0"),
    (["run", "{video}", "--out", "{ws}", "--frames.blur-ratio", "-1"], "--frames.blur-ratio -1"),
    (["run", "{video}", "--out", "{ws}", "--export.min-opacity", "2"], "--export.min-opacity 2"),
    (["run", "{video}", "--out", "{ws}", "--train.iterations", "99999999999999999999"], "--train.iterations"),
])
def test_bad_option_values_are_refused_before_any_record_changes(finished_records, tmp_path, capsys, args, option):
    """Issue 42 #5 (and #12's iterations and blur ratio): exit 2, the option named, every stage record as it was."""
    ws, records = finished_records
    video = tmp_path / "video.mp4"
    video.write_bytes(b"\0" * 64)
    code = main([a.format(ws=ws.root, video=video) for a in args])
    _one_error_line(capsys.readouterr().err, option)
    assert code == 2
    assert {p: p.read_bytes() for p in records} == records
    assert sorted(p.name for p in record_path(ws, "x").parent.iterdir()) == sorted(p.name for p in records)


@pytest.mark.parametrize("option", ["--ground-truth", "--segment.import-masks", "--poses.import-transforms"])
def test_missing_option_paths_are_refused_at_the_start(tmp_path, capsys, option):
    """Issue 42 #8: a path option that names nothing stops `run` before the first stage, naming the option."""
    video = tmp_path / "video.mp4"
    video.write_bytes(b"\0" * 64)
    code = main(["run", str(video), "--out", str(tmp_path / "ws"), option, str(tmp_path / "missing")])
    _one_error_line(capsys.readouterr().err, "missing", option)
    assert code == 2 and not (tmp_path / "ws" / ".plantsplat").exists()


def test_batch_refuses_a_missing_ground_truth_at_the_start(tmp_path, capsys):
    manifest = tmp_path / "plants.csv"
    manifest.write_text("plant_id,input\np1,nowhere.mp4\n")
    code = main(["batch", str(manifest), "--out", str(tmp_path / "out"), "--ground-truth", str(tmp_path / "gt.csv")])
    _one_error_line(capsys.readouterr().err, "gt.csv", "--ground-truth")
    assert code == 2 and not (tmp_path / "out").exists()


def test_a_capture_folders_own_masks_are_never_overwritten(synth_capture, tmp_path, capsys):
    """Issue 42 #3: `run capX/video.mp4 --out capX` on a folder holding the user's masks/ is refused (exit 2, one
    line) before any stage runs, as is `segment capX --force`; the masks are left as they were."""
    rendered = synth_capture()
    capsys.readouterr()  # the capture's own log, when it was rendered here
    cap = tmp_path / "capX"
    cap.mkdir()
    shutil.copy(rendered / "video.mp4", cap / "video.mp4")
    shutil.copytree(rendered / "masks", cap / "masks")
    before = {p.name: p.read_bytes() for p in (cap / "masks").iterdir()}
    assert main(["run", str(cap / "video.mp4"), "--out", str(cap)]) == 2
    _one_error_line(capsys.readouterr().err, "masks", "segment stage did not write")
    assert not (cap / "images").exists() and not (cap / ".plantsplat").exists()
    assert main(["segment", str(cap), "--force"]) == 2
    _one_error_line(capsys.readouterr().err, "masks")
    assert {p.name: p.read_bytes() for p in (cap / "masks").iterdir()} == before


def test_out_pointing_at_a_file_is_exit_2(tmp_path, capsys):
    """Issue 42 #12: `--out` naming a file (or a path under one) is an impossible argument: exit 2, one line."""
    video = tmp_path / "video.mp4"
    video.write_bytes(b"\0" * 64)
    (tmp_path / "afile").write_text("mine")
    for out in (tmp_path / "afile", tmp_path / "afile" / "ws"):
        assert main(["run", str(video), "--out", str(out)]) == 2
        _one_error_line(capsys.readouterr().err, "afile", "not a folder")
    assert (tmp_path / "afile").read_text() == "mine"


@pytest.mark.parametrize("args, words", [
    (["run", "v.mp4", "--out", "ws", "--train.iteratons", "5"], ["--train.iteratons", "did you mean --train.iterations"]),
    (["run", "v.mp4", "--out", "ws", "--train.iterations", "abc"], ["--train.iterations", "abc"]),
    (["frames", "v.mp4", "--out", "ws", "--num", "1.5"], ["--num", "1.5"]),
    (["rnu", "v.mp4"], ["rnu", "run"]),
])
def test_typos_and_non_integers_are_one_line(capsys, args, words):
    """Issue 42 #12: tyro's multi-line boxes become one line, with the option it suggests and where help is."""
    assert main(args) == 2
    captured = capsys.readouterr()
    _one_error_line(captured.err + captured.out, *words, "--help")


def test_traits_csv_cells_are_not_formulas():
    """Issue 42 #12: a plant id (the workspace's name) starting with = + - @ is not run by a spreadsheet."""
    import csv
    import io

    from plantsplat.traits.stage import traits_csv_text

    for pid in ("=HYPERLINK(\"http://x\")", "+1", "-2+3", "@SUM(A1)"):
        rows = list(csv.reader(io.StringIO(traits_csv_text({"height_cm": 12.5, "quality": "ok"}, pid))))
        assert rows[1][0] == "'" + pid and rows[1][1] == "12.5000"
    rows = list(csv.reader(io.StringIO(traits_csv_text({"height_cm": -1.0}, "plant01"))))
    assert rows[1][:2] == ["plant01", "-1.0000"]  # numbers stay numbers


def test_batch_no_report_writes_no_report(tmp_path):
    """Issue 42 #10: `batch --no-report` writes no report.html (the plants' nor the batch's)."""
    manifest = tmp_path / "plants.csv"
    manifest.write_text("plant_id,input\np1,nowhere.mp4\n")
    main(["batch", str(manifest), "--out", str(tmp_path / "out"), "--no-report"])
    assert (tmp_path / "out" / "traits.csv").is_file() and not (tmp_path / "out" / "report.html").exists()


def test_one_process_per_workspace_and_a_stale_lock_is_taken_over(tmp_path, capsys):
    """Issue 42 #6: while another process works on a workspace, `run` and a stage command are refused with one line
    naming it (no stage record touched); once that process is dead its lock is taken over."""
    import subprocess
    import sys

    ws = tmp_path / "ws"
    ws.mkdir()
    video = tmp_path / "video.mp4"
    video.write_bytes(b"\0" * 64)
    hold = "import sys, time\nfrom plantsplat.lock import workspace_lock\nwith workspace_lock(sys.argv[1]):\n" \
           "    print('held', flush=True)\n    time.sleep(120)\n"
    other = subprocess.Popen([sys.executable, "-c", hold, str(ws)], stdout=subprocess.PIPE, text=True)
    try:
        assert other.stdout.readline().strip() == "held"
        for args in (["run", str(video), "--out", str(ws)], ["export", str(ws)]):
            assert main(args) == 1
            _one_error_line(capsys.readouterr().err, f"in use by process {other.pid}")
        assert not (ws / ".plantsplat" / "stages").exists()
    finally:
        other.kill()  # SIGKILL: no clean-up, the lock file stays behind
        other.wait()
    assert (ws / ".plantsplat" / "lock").is_file()
    assert main(["export", str(ws)]) == 1  # runs (and fails: nothing trained), no longer refused
    err = capsys.readouterr().err
    assert "in use" not in err and "no trained model" in err
    assert record_path(Workspace(ws), "export").is_file() and not (ws / ".plantsplat" / "lock").exists()


def test_a_damaged_jpeg_is_named_not_printed_raw(tmp_path, capfd):
    """Issue 42 #12: libjpeg's "Premature end of JPEG file" does not reach the terminal raw: one warning names the
    image (which is used as far as it could be decoded)."""
    import cv2
    import numpy as np

    photos = tmp_path / "photos"
    photos.mkdir()
    rng = np.random.default_rng(0)
    for i in range(10):
        ok, data = cv2.imencode(".jpg", rng.integers(0, 255, (120, 160, 3), dtype=np.uint8))
        (photos / f"img_{i:02d}.jpg").write_bytes(data.tobytes()[: len(data) // 2] if i == 4 else data.tobytes())
    main(["frames", str(photos), "--out", str(tmp_path / "ws"), "--num", "10"])
    err = capfd.readouterr().err
    raw = [ln for ln in err.splitlines() if "JPEG" in ln and "img_04.jpg" not in ln and "damaged" not in ln]
    assert raw == [] and "img_04.jpg:damagedimage(thefileiscutshort)" in "".join(err.split())  # wrapped

"""Batch: manifest problems are named, one plant's failure does not stop the others, exit code."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from plantsplat.batch import BatchConfig, read_manifest, run_batch
from plantsplat.cli import main
from plantsplat.errors import PlantsplatError


def _manifest(tmp_path: Path, rows: list[tuple[str, str]]) -> Path:
    p = tmp_path / "plants.csv"
    with p.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["plant_id", "input"])
        w.writerows(rows)
    return p


def test_manifest_problems_are_named(tmp_path):
    (tmp_path / "empty_a").mkdir()
    m = _manifest(
        tmp_path,
        [("a", "empty_a"), ("a", "empty_a"), ("b", "missing.mp4"), ("", "x"), ("bad id!", "empty_a"), ("c", "")],
    )
    rows = read_manifest(m)
    by = [(r.plant_id, r.problem) for r in rows]
    assert by[0] == ("a", None)
    assert "duplicate plant_id 'a'" in by[1][1]
    assert "missing.mp4" in by[2][1] and "not found" in by[2][1]
    assert "no plant_id" in by[3][1]
    assert "must be letters" in by[4][1]
    assert "no input" in by[5][1]


def test_manifest_without_columns(tmp_path):
    p = tmp_path / "m.csv"
    p.write_text("id,video\na,b.mp4\n")
    with pytest.raises(PlantsplatError, match="plant_id and input"):
        read_manifest(p)


def test_each_plant_runs_in_a_process_of_its_own(tmp_path, monkeypatch):
    """A process that has run one plant carries state into the next: every plant gets a fresh worker process, with one
    worker as with several."""
    import plantsplat.batch as B

    made = []

    class Recording(B.ProcessPoolExecutor):
        def __init__(self, *args, **kwargs):
            made.append(kwargs)
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(B, "ProcessPoolExecutor", Recording)
    (tmp_path / "p1").mkdir()
    run_batch(_manifest(tmp_path, [("p1", "p1")]), tmp_path / "out", BatchConfig(workers=1))
    assert made and all(k.get("max_tasks_per_child") == 1 for k in made)


def test_batch_exit_codes_are_the_readmes():
    """0: every plant succeeded; 4: the only failures are results that failed their checks; 1: a run failed."""
    from plantsplat.commands.batch import batch_exit_code

    ok = {"plant_id": "a", "status": "ok", "traits": {"quality": "ok"}}
    judged = {"plant_id": "b", "status": "failed", "traits": {"quality": "failed"}}
    broken = {"plant_id": "c", "status": "failed", "error": "poses: too few frames registered"}
    skipped = {"plant_id": "d", "status": "skipped", "error": "nope.mov: not found"}
    assert batch_exit_code({"n_failed": 0, "plants": [ok, ok]}) == 0
    assert batch_exit_code({"n_failed": 1, "plants": [ok, judged]}) == 4
    assert batch_exit_code({"n_failed": 2, "plants": [judged, broken]}) == 1
    assert batch_exit_code({"n_failed": 1, "plants": [ok, skipped]}) == 1


def test_failing_plant_does_not_stop_others_and_exit_code(tmp_path):
    # two plants whose input folders hold no images: both fail in the frames stage, each with its reason;
    # a missing file is skipped with its reason; the batch still writes its tables.
    (tmp_path / "p1").mkdir()
    (tmp_path / "p2").mkdir()
    (tmp_path / "p2" / "notes.txt").write_text("no images here")
    m = _manifest(tmp_path, [("p1", "p1"), ("p2", "p2"), ("p3", "nope.mov")])
    out = tmp_path / "out"
    summary = run_batch(m, out, BatchConfig(workers=1))
    status = {p["plant_id"]: p for p in summary["plants"]}
    assert status["p1"]["status"] == "failed" and "p1" in status["p1"]["error"]
    assert status["p2"]["status"] == "failed"
    assert status["p3"]["status"] == "skipped" and "nope.mov" in status["p3"]["error"]
    rows = list(csv.DictReader((out / "traits.csv").open()))
    assert [r["plant_id"] for r in rows] == ["p1", "p2", "p3"]
    assert (out / "batch.json").is_file()
    # the CLI returns 1 when any plant failed
    assert main(["batch", str(m), "--out", str(out)]) == 1

"""The shared core: CLI registry and error handling, atomic I/O, ground truth readers, trait definitions,
the runner's resume logic."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from plantsplat import traitdefs
from plantsplat.cli import main
from plantsplat.errors import PlantsplatError
from plantsplat.groundtruth import (
    compare_traits,
    load_ground_truth,
    read_ground_truth_csv,
)
from plantsplat.io import (
    atomic_path,
    read_image,
    read_json,
    write_image_atomic,
    write_json_atomic,
)
from plantsplat.workspace import prepare_output_dir


def test_version_and_help(capsys):
    assert main(["--version"]) == 0
    assert "plantsplat" in capsys.readouterr().out
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "doctor" in out


def test_unknown_option_is_usage_error(capsys):
    assert main(["doctor", "--no-such-option"]) == 2


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "a.json"
    write_json_atomic(target, {"x": np.float32(1.5), "arr": np.arange(3)})
    assert read_json(target) == {"x": 1.5, "arr": [0, 1, 2]}
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    assert read_json(target)["x"] == 1.5  # old content kept
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json"]  # no temp litter


def test_corrupt_json_is_one_line_error(tmp_path):
    p = tmp_path / "bad.json"
    p.write_text("{not json")
    with pytest.raises(PlantsplatError, match="bad.json: not valid JSON"):
        read_json(p)


def test_image_roundtrip_rgb_rgba_gray(tmp_path):
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 255, (5, 7, 3), dtype=np.uint8)
    rgba = rng.integers(0, 255, (5, 7, 4), dtype=np.uint8)
    gray = rng.integers(0, 255, (5, 7), dtype=np.uint8)
    for name, img, mode in [("c.png", rgb, "rgb"), ("d.png", rgba, "rgba"), ("e.png", gray, "gray")]:
        write_image_atomic(tmp_path / name, img)
        np.testing.assert_array_equal(read_image(tmp_path / name, mode), img)
    (tmp_path / "broken.png").write_bytes(b"not a png")
    with pytest.raises(PlantsplatError, match="broken.png"):
        read_image(tmp_path / "broken.png")


def test_prepare_output_dir_refuses_non_empty(tmp_path):
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "keep.txt").write_text("mine")
    with pytest.raises(PlantsplatError, match="not empty") as info:
        prepare_output_dir(tmp_path / "x")
    assert info.value.exit_code == 2
    prepare_output_dir(tmp_path / "x", force=True)
    assert (tmp_path / "x" / "keep.txt").read_text() == "mine"  # --force never deletes


def test_traitdefs_against_independent_formulas():
    rng = np.random.default_rng(1)
    # an anisotropic, rotated cloud: widths along its own axes are known
    # a regular grid filling a 20 x 6 x 8 box: its PCA axes are the box axes, its hull the box
    g = np.meshgrid(np.linspace(-10, 10, 41), np.linspace(-3, 3, 13), np.linspace(0, 8, 9), indexing="ij")
    pts = np.stack([a.ravel() for a in g], axis=1)
    pts = pts[rng.permutation(len(pts))]
    a = np.deg2rad(30)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    pts = pts @ R.T
    w1, w2 = traitdefs.pca_widths(pts)
    assert w1 == pytest.approx(20, abs=0.05) and w2 == pytest.approx(6, abs=0.05)
    assert traitdefs.plant_height(pts) == pytest.approx(8.0)
    tall = np.zeros((1001, 3))
    tall[:, 2] = np.linspace(0, 100, 1001)
    assert traitdefs.plant_height(tall, trim=0.1) == pytest.approx(80.0)
    assert traitdefs.canopy_volume(pts) == pytest.approx(20 * 6 * 8, rel=1e-9)
    assert traitdefs.canopy_area(pts) == pytest.approx(120, rel=1e-9)
    with pytest.raises(ValueError):
        traitdefs.pca_widths(np.zeros((2, 3)))
    flat = pts.copy()
    flat[:, 2] = 4.0  # a cloud in one plane (exported flat): no volume, its area as before
    assert traitdefs.canopy_volume(flat) == 0.0 and traitdefs.canopy_area(flat) == pytest.approx(120, rel=1e-9)
    line = np.zeros((50, 3))
    line[:, 2] = np.linspace(0, 5, 50)  # a stalk seen straight: no area
    assert traitdefs.canopy_area(line) == 0.0


def test_a_splat_ply_with_no_gaussians_reads_as_empty(tmp_path):
    """An export with no Gaussian left (all under the opacity cut) is read as an empty cloud, which the traits stage
    then marks failed (too few points), not a reshape error."""
    from plantsplat.ply import read_splat, read_splat_extent_cloud

    props = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", *[f"f_rest_{i}" for i in range(9)], "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    path = tmp_path / "splat.ply"
    path.write_bytes(("ply\nformat binary_little_endian 1.0\nelement vertex 0\n"
                      + "".join(f"property float {p}\n" for p in props) + "end_header\n").encode())
    g = read_splat(path)
    assert g["means"].shape == (0, 3) and g["shN"].shape == (0, 3, 3)
    assert read_splat_extent_cloud(path, 0.1, 2.0)["xyz"].shape == (0, 3)


def test_ground_truth_csv_problems(tmp_path):
    p = tmp_path / "gt.csv"
    p.write_text(
        "plant_id,height_cm,width1_cm\n"
        "a,20,30\n"
        "b,abc,30\n"
        ",1,2\n"
        "a,1,1\n"
        "c,,25\n"
    )
    rows, problems = read_ground_truth_csv(p)
    assert rows == {"a": {"height_cm": 20.0, "width1_cm": 30.0}, "c": {"width1_cm": 25.0}}
    assert len(problems) == 3 and any("'b'" in q for q in problems)
    assert load_ground_truth(p, "c") == {"width1_cm": 25.0}
    with pytest.raises(PlantsplatError, match="'b'"):
        load_ground_truth(p, "b")
    cmp = compare_traits({"height_cm": 22.0}, {"height_cm": 20.0, "width1_cm": 30.0})
    assert cmp["height_cm"]["pct_error"] == pytest.approx(10.0)
    assert cmp["width1_cm"]["estimate"] is None


def test_ground_truth_json(tmp_path):
    p = tmp_path / "ground_truth.json"
    p.write_text(json.dumps({"height_cm": 21.0, "fruit_count": 3, "frames": []}))
    assert load_ground_truth(p) == {"height_cm": 21.0, "fruit_count": 3.0}


def test_every_command_has_working_help(capsys):
    from plantsplat.cli import discover_commands

    names = [c.name for c in discover_commands()]
    for expected in ["synth", "frames", "segment", "poses", "train", "export", "traits", "evaluate", "run", "demo",
                     "batch", "report", "doctor"]:
        assert expected in names
    for name in names:
        assert main([name, "--help"]) == 0, name
        out = capsys.readouterr().out
        assert f"plantsplat {name}" in out


@pytest.mark.parametrize("err", ["ENOSPC", "EACCES", "EROFS"])
def test_write_failures_are_said_in_words(tmp_path, monkeypatch, capsys, err):
    """A full disk or a folder without write permission gives one line that says so, from any writer."""
    import errno
    import tempfile

    def refuse(*a, **k):
        raise OSError(getattr(errno, err), os.strerror(getattr(errno, err)))

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    with pytest.raises(PlantsplatError) as exc:
        write_json_atomic(tmp_path / "out.json", {"a": 1})
    words = {"ENOSPC": "the disk is full", "EACCES": "permission denied", "EROFS": "read-only"}[err]
    assert words in str(exc.value) and "out.json" in str(exc.value) and "\n" not in str(exc.value)


def test_checkpoint_on_a_full_disk(tmp_path, monkeypatch):
    torch = pytest.importorskip("torch")
    from plantsplat.train.checkpoint import save_checkpoint

    def full(*a, **k):
        raise RuntimeError("[enforce fail at inline_container.cc:595] . unexpected pos 4416 vs 4306")

    monkeypatch.setattr(torch, "save", full)
    with pytest.raises(PlantsplatError, match="checkpoint.pt: the disk is full"):
        save_checkpoint(tmp_path / "checkpoint.pt", 1, {}, {}, {}, {})
    assert list(tmp_path.iterdir()) == []


def test_stage_meter_counts_the_cpu_of_waited_for_children():
    """A stage's CPU seconds include what it ran in processes it waited for (the synthetic video's encoder), which
    the process's own CPU time misses; an idle wait adds wall time, not CPU time."""
    import subprocess
    import sys
    import time

    from plantsplat.resources import StageMeter

    busy = "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.3: pass"
    with StageMeter() as m:
        subprocess.run([sys.executable, "-c", busy], check=True)
        time.sleep(0.2)
    assert 0.3 <= m.cpu_seconds < m.seconds and m.peak_rss_mb > 0


def test_an_image_cut_short_gives_one_clear_line(tmp_path, capfd):
    """A PNG cut short is an error naming it, and libpng's "libpng error: Read Error" does not reach the terminal raw;
    a whole image is read as it is."""
    import cv2

    from plantsplat.io import cut_short, read_image

    ok, data = cv2.imencode(".png", np.random.default_rng(0).integers(0, 255, (64, 64, 3), dtype=np.uint8))
    whole, short = tmp_path / "whole.png", tmp_path / "short.png"
    whole.write_bytes(data.tobytes())
    short.write_bytes(data.tobytes()[: len(data) // 2])
    assert not cut_short(whole) and cut_short(short) and not cut_short(tmp_path / "missing.png")
    assert read_image(whole).shape == (64, 64, 3)
    with pytest.raises(PlantsplatError, match="short.png: unreadable"):
        read_image(short)
    assert "libpng" not in capfd.readouterr().err


def test_images_read_in_threads_leave_stderr_where_it_was(tmp_path):
    """The segment stage reads frames in two threads (GrabCut in a pool), and each quiet read sends the process's
    stderr to a scratch file for a moment to catch libjpeg's complaints. Two such moments overlapping left stderr in a
    deleted scratch file for the rest of the run: every log line after the segment stage was lost, the traits table
    and a failed result's message among them (2026-11-27, every end-to-end run's log). A whole image is now read
    without touching stderr."""
    import subprocess
    import sys

    import cv2

    png = tmp_path / "frame.png"
    cv2.imwrite(str(png), np.zeros((64, 64, 3), np.uint8))
    code = ("import sys, time; from concurrent.futures import ThreadPoolExecutor; from plantsplat.io import read_image\n"
            "with ThreadPoolExecutor(4) as pool:\n"
            f"    reads = pool.map(lambda _: read_image({str(png)!r}), range(2000))\n"
            "    for i in range(200): print(f'line {i}', file=sys.stderr, flush=True); time.sleep(0.001)\n"
            "    list(reads)\n"
            "print('still said', file=sys.stderr)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and "still said" in out.stderr, out.stderr
    # what another thread says meanwhile (a log line, a progress bar) reaches stderr and is not taken for the
    # decoder's complaint (the demo's log, 2026-11-27: "frame_00000.png: damaged image (INFO detecting ...)")
    assert all(f"line {i}\n" in out.stderr for i in range(200)) and "damaged" not in out.stderr, out.stderr

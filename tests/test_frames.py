"""Frame extraction: rotation, sharpest-per-stretch choice, duplicates, folders, resume, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from plantsplat.errors import PlantsplatError
from plantsplat.frames import FramesConfig
from plantsplat.frames import stage as extraction
from plantsplat.frames.select import sharpness, working_size
from plantsplat.io import read_json
from plantsplat.pipeline import frames_stage
from plantsplat.workspace import Workspace


def _pattern(i: int, w: int, h: int) -> np.ndarray:
    """A textured frame that changes with i; a white band marks the top-left (display) corner."""
    rng = np.random.default_rng(i)
    img = cv2.resize((rng.random((h // 8, w // 8, 3)) * 255).astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST)
    img[: h // 6, : w // 6] = 255
    return img


def _write_video(path: Path, frames: list[np.ndarray], rotation: float = 0.0, fps: int = 24) -> Path:
    import av

    h, w = frames[0].shape[:2]
    with av.open(str(path), "w") as c:
        s = c.add_stream("libx264", rate=fps)
        s.width, s.height, s.pix_fmt = w, h, "yuv420p"
        s.options = {"preset": "ultrafast", "crf": "12"}
        if rotation:
            s.set_display_rotation(rotation)
        for f in frames:
            for p in s.encode(__import__("av").VideoFrame.from_ndarray(f, format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    return path


def test_working_size_and_sharpness():
    assert working_size(1080, 1920, 960) == (540, 960)
    assert working_size(400, 300, 960) == (400, 300)  # never upscaled
    sharp = _pattern(0, 64, 64)[..., 0]
    assert sharpness(sharp) > 5 * sharpness(cv2.GaussianBlur(sharp, (0, 0), 3))


def test_video_rotation_and_spread(tmp_path):
    # stored landscape 160x96, displayed rotated 90 deg clockwise (a phone held upright)
    frames = [_pattern(i, 160, 96) for i in range(30)]
    video = _write_video(tmp_path / "v.mp4", frames, rotation=-90)
    ws = Workspace(tmp_path / "ws")
    info = extraction.run(ws, FramesConfig(num=10, max_size=80), video)
    assert info["kind"] == "video" and info["rotation"] == 270
    assert info["working_size"] == [48, 80]  # portrait
    names = ws.image_names()
    assert len(names) == 10 == len(info["frames"])
    img = cv2.imread(str(ws.images_dir / names[0]))
    assert img.shape[:2] == (80, 48)
    # the white band (stored top-left) is displayed at the top-right after a clockwise turn
    expected = np.rot90(frames[info["frames"][0]["source_index"]], k=-1)
    expected = cv2.resize(expected, (48, 80), interpolation=cv2.INTER_AREA)
    got = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    assert np.mean(np.abs(got.astype(int) - expected.astype(int))) < 12
    assert got[:6, -6:].mean() > 200 and got[-6:, :6].mean() < 250
    idx = [f["source_index"] for f in info["frames"]]
    assert idx == sorted(idx) and idx[0] < 3 and idx[-1] >= 27  # spread over the whole capture
    data = json.loads(ws.frames_json.read_text())
    assert data["source_size"] == [160, 96] and data["total_source_frames"] == 30


def test_picks_sharpest_frame_of_each_stretch(tmp_path):
    frames = []
    for i in range(40):
        f = _pattern(i, 128, 128)
        if i % 5 != 2:  # only the third frame of each stretch of 5 is sharp
            f = cv2.GaussianBlur(f, (0, 0), 2.5)
        frames.append(f)
    video = _write_video(tmp_path / "v.mp4", frames)
    info = extraction.run(tmp_path / "ws", FramesConfig(num=8, max_size=128), video)
    assert [f["source_index"] for f in info["frames"]] == [5 * k + 2 for k in range(8)]


def test_drops_blurred_and_duplicate_frames(tmp_path):
    frames = [_pattern(i, 96, 96) for i in range(12)]
    frames[4] = cv2.GaussianBlur(frames[4], (0, 0), 6)  # a whole stretch blurred
    frames[8] = frames[7].copy()  # the camera stood still
    d = tmp_path / "imgs"
    d.mkdir()
    for i, f in enumerate(frames):
        cv2.imwrite(str(d / f"img_{i}.png"), f)
    info = extraction.run(tmp_path / "ws", FramesConfig(num=12, min_frames=4), d)
    kept = [f["source_index"] for f in info["frames"]]
    dropped = {x["source_index"]: x["reason"] for x in info["dropped"]}
    assert 4 not in kept and "blurred" in dropped[4]
    assert 8 not in kept and "duplicate" in dropped[8]
    assert len(kept) == 10
    assert info["frames"][0]["source_name"] == "img_0.png"  # natural order: img_2 before img_10


def test_folder_natural_order_unreadable_and_sizes(tmp_path):
    d = tmp_path / "imgs"
    d.mkdir()
    for i in (1, 2, 10):
        cv2.imwrite(str(d / f"p{i}.jpg"), _pattern(i, 64, 48))
    (d / "p3.jpg").write_bytes(b"not a jpeg")
    info = extraction.run(tmp_path / "ws", FramesConfig(num=10, min_frames=2), d)
    assert [f["source_name"] for f in info["frames"]] == ["p1.jpg", "p2.jpg", "p10.jpg"]
    assert info["unreadable"] == ["p3.jpg"]
    cv2.imwrite(str(d / "p11.jpg"), _pattern(11, 48, 64))
    with pytest.raises(PlantsplatError, match="p11.jpg: size 48x64 differs"):
        extraction.run(tmp_path / "ws2", FramesConfig(num=10, min_frames=2), d)


def test_resume_and_protection(tmp_path):
    video = _write_video(tmp_path / "v.mp4", [_pattern(i, 64, 64) for i in range(20)])
    ws = Workspace(tmp_path / "ws")
    frames_stage(ws, video, FramesConfig(num=10))
    first = ws.images_dir / "frame_00000.png"
    stamp = first.stat().st_mtime_ns
    assert frames_stage(ws, video, FramesConfig(num=10))["up_to_date"]  # same input and options: nothing redone
    assert first.stat().st_mtime_ns == stamp
    info = frames_stage(ws, video, FramesConfig(num=9))  # changed option: the stage runs again, images/ replaced whole
    assert len(ws.image_names()) == 9 == len(info["frames"])  # no stale frame_00009.png


def test_images_not_written_by_the_stage_are_kept(tmp_path):
    video = _write_video(tmp_path / "v.mp4", [_pattern(i, 64, 64) for i in range(20)])
    ws = Workspace(tmp_path / "ws")
    ws.images_dir.mkdir(parents=True)
    cv2.imwrite(str(ws.images_dir / "mine.png"), _pattern(0, 64, 64))
    with pytest.raises(PlantsplatError, match="did not write"):
        frames_stage(ws, video, FramesConfig(num=10))
    assert ws.image_names() == ["mine.png"]


def test_input_inside_the_output_is_refused(tmp_path):
    """A folder given as input is never the one the stage replaces, even with --force (issue 34, case 3)."""
    ws = Workspace(tmp_path / "ws")
    ws.images_dir.mkdir(parents=True)
    for i in range(12):
        cv2.imwrite(str(ws.images_dir / f"img_{i:02d}.png"), _pattern(i, 64, 64))
    for src in (ws.images_dir, ws.root):
        with pytest.raises(PlantsplatError, match="the folder this stage writes") as exc:
            frames_stage(ws, src, FramesConfig(num=5, min_frames=2), force=True)
        assert "\n" not in str(exc.value)
    assert len(ws.image_names()) == 12


def test_interrupted_extraction_leaves_nothing_half_written(tmp_path, monkeypatch, interrupted_after):
    """Ctrl-C while writing images leaves images/ as it was; the same command then finishes (issue 34, case 4)."""
    video = _write_video(tmp_path / "v.mp4", [_pattern(i, 64, 64) for i in range(20)])
    ws = Workspace(tmp_path / "ws")
    real = extraction.write_image_atomic
    monkeypatch.setattr(extraction, "write_image_atomic", interrupted_after(real, 4))
    with pytest.raises(KeyboardInterrupt):
        frames_stage(ws, video, FramesConfig(num=10))
    assert ws.image_names() == [] and not ws.frames_json.exists()
    assert [p.name for p in ws.root.iterdir()] == [".plantsplat"]  # no half-written folder left beside images/
    monkeypatch.setattr(extraction, "write_image_atomic", real)
    info = frames_stage(ws, video, FramesConfig(num=10))
    assert len(ws.image_names()) == 10 == len(info["frames"])


def test_ctrl_c_is_exit_130_in_one_line_and_the_command_resumes(tmp_path, monkeypatch, capsys, interrupted_after):
    """The README's exit code 130: Ctrl-C ends the command with one line, no traceback; the same command finishes.
    A Ctrl-C that lands inside a C library's callback (raised as a SystemError caused by it) is the same."""
    from plantsplat.cli import main

    video = _write_video(tmp_path / "v.mp4", [_pattern(i, 64, 64) for i in range(20)])
    real = extraction.write_image_atomic
    args = ["frames", str(video), "--out", str(tmp_path / "ws"), "--num", "10"]
    monkeypatch.setattr(extraction, "write_image_atomic", interrupted_after(real, 4))
    assert main(args) == 130

    def from_c(*a, **k):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as exc:
            raise SystemError("<built-in function> returned a result with an exception set") from exc

    monkeypatch.setattr(extraction, "write_image_atomic", from_c)
    assert main(args) == 130
    err = capsys.readouterr().err
    assert err.count("interrupted: finished outputs are kept; re-run the same command to resume") == 2
    assert "Traceback" not in err
    monkeypatch.setattr(extraction, "write_image_atomic", real)
    assert main(args) == 0 and len(Workspace(tmp_path / "ws").image_names()) == 10


def test_full_disk_is_said_in_words(tmp_path, monkeypatch):
    import errno

    video = _write_video(tmp_path / "v.mp4", [_pattern(i, 64, 64) for i in range(20)])

    def full(path, img):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(extraction, "write_image_atomic", full)
    with pytest.raises(PlantsplatError, match="disk is full") as exc:
        frames_stage(Workspace(tmp_path / "ws"), video, FramesConfig(num=10))
    assert "\n" not in str(exc.value)


@pytest.mark.parametrize("kind", ["missing", "empty_video", "garbage_video", "empty_folder", "too_few"])
def test_bad_input(tmp_path, kind):
    ws = Workspace(tmp_path / "ws")
    if kind == "missing":
        src, msg = tmp_path / "nope.mp4", "no such file"
    elif kind == "empty_video":
        src, msg = tmp_path / "e.mp4", "e.mp4"
        src.write_bytes(b"")
    elif kind == "garbage_video":
        src, msg = tmp_path / "g.mov", "g.mov"
        src.write_bytes(np.random.default_rng(0).bytes(5000))
    elif kind == "empty_folder":
        src, msg = tmp_path / "d", "no images found"
        src.mkdir()
        (src / "notes.txt").write_text("x")
    else:
        src, msg = _write_video(tmp_path / "short.mp4", [_pattern(i, 64, 64) for i in range(3)]), "only 3 usable frames"
    with pytest.raises(PlantsplatError, match=msg) as exc:
        extraction.run(ws, FramesConfig(num=10), src)
    assert "\n" not in str(exc.value)
    assert not ws.frames_json.exists()


def test_cli_frames(tmp_path, capsys):
    from plantsplat.cli import main

    video = _write_video(tmp_path / "v.mp4", [_pattern(i, 64, 96) for i in range(16)])
    assert main(["frames", str(video), "--out", str(tmp_path / "ws"), "--num", "8"]) == 0
    assert len(Workspace(tmp_path / "ws").image_names()) == 8
    assert main(["frames", str(tmp_path / "missing.mp4"), "--out", str(tmp_path / "ws2")]) == 1
    err = capsys.readouterr().err
    assert "missing.mp4" in err and "Traceback" not in err


def test_a_capture_short_of_what_registration_needs_is_told_at_the_start(tmp_path, capsys):
    """Issue 42: too few frames or too small ones are said when the capture is read (the frames stage, the first of
    `run`), each in one line that names what to film, and recorded in frames.json; a capture that has enough is not."""
    from plantsplat.cli import main

    video = _write_video(tmp_path / "v.mp4", [_pattern(i, 64, 96) for i in range(16)])
    assert main(["frames", str(video), "--out", str(tmp_path / "ws"), "--num", "8"]) == 0
    err = " ".join(capsys.readouterr().err.split())  # the log wraps long lines
    assert "capture: 8 frames: a capture needs at least 100" in err
    assert "capture: frames of 64x96 px: the short side should be at least 480 px (film at 1080p or more)" in err
    assert len(read_json(Workspace(tmp_path / "ws").frames_json)["shortfalls"]) == 2
    big = _write_video(tmp_path / "big.mp4", [_pattern(i, 480, 640) for i in range(110)])
    assert main(["frames", str(big), "--out", str(tmp_path / "ws2"), "--num", "105"]) == 0
    assert "capture:" not in capsys.readouterr().err
    assert read_json(Workspace(tmp_path / "ws2").frames_json)["shortfalls"] == []


def test_a_video_with_overwritten_bytes_is_the_videos_fault(synth_capture, tmp_path, capfd):
    """Issue 42 #4: an mp4 whose middle was overwritten decodes without an exception into concealed garbage frames;
    the frames stage refuses it (exit 1, one line) as the video's fault, and no decoder message reaches the terminal
    raw. The intact video passes."""
    from plantsplat.cli import main

    video = synth_capture() / "video.mp4"
    data = bytearray(video.read_bytes())
    rng = np.random.default_rng(0)
    for frac in (0.3, 0.5, 0.7):
        at = int(len(data) * frac)
        data[at:at + 300] = rng.integers(0, 256, 300, dtype=np.uint8).tobytes()
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(bytes(data))
    capfd.readouterr()
    assert main(["frames", str(bad), "--out", str(tmp_path / "ws"), "--num", "36"]) == 1
    err = capfd.readouterr().err
    assert "the video is damaged" in err and "decoder reported errors" in err and "slowly" not in err
    assert not any(ln.startswith(("error while decoding", "left block")) for ln in err.splitlines())
    assert not (tmp_path / "ws" / "images").exists()
    assert main(["frames", str(video), "--out", str(tmp_path / "ws2"), "--num", "36"]) == 0

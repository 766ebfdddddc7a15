"""The cube's markers: detection, X-junctions and the edge-shift correction, on markers drawn with known geometry."""

from __future__ import annotations

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from plantsplat.cube import CubeSpec  # noqa: E402
from plantsplat.markers import (  # noqa: E402
    Markers,
    detect_frames,
    edge_shift_px,
    junctions,
    marker_cells,
    markers_in_image,
    read_markers,
    shift_corners,
    write_markers,
)


def draw_marker(marker_id: int, corners: np.ndarray, erode_px: float, size=(480, 480), ss: int = 8) -> np.ndarray:
    """A gray frame showing one marker (white card around it) whose corners land on ``corners`` [4, 2], with its
    black print eroded by ``erode_px`` pixels, drawn ``ss`` times larger and averaged down (pixel centres at
    integer coordinates)."""
    cube = CubeSpec()
    n = marker_cells(marker_id, cube).shape[0]
    print_px = 60 * n
    printed = cv2.aruco.generateImageMarker(cube.aruco_dictionary(), marker_id, print_px, borderBits=1)
    # the print's outer edges, in the pixel-centre coordinates of the card (the print sits 20 px inside it)
    src = np.array([[0, 0], [print_px, 0], [print_px, print_px], [0, print_px]], np.float32) + 19.5
    dst = ((corners + 0.5) * ss - 0.5).astype(np.float32)  # the same points in the drawing, ss times larger
    Hc = cv2.getPerspectiveTransform(src, dst)
    W, Hh = size[0] * ss, size[1] * ss
    card = np.full((print_px + 40, print_px + 40), 255, np.uint8)
    card[20:-20, 20:-20] = printed
    big = cv2.warpPerspective(card, Hc, (W, Hh), flags=cv2.INTER_NEAREST, borderValue=90)
    k = int(round(erode_px * ss))
    if k > 0:  # black shrinks: white grows
        big = cv2.dilate(big, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * k + 1, 2 * k + 1)))
    small = cv2.resize(big, size, interpolation=cv2.INTER_AREA)
    return cv2.GaussianBlur(small, (0, 0), 0.7)


CORNERS = np.array([[140.0, 120.0], [350.0, 135.0], [335.0, 340.0], [130.0, 325.0]])


def test_junctions_of_a_known_marker():
    cells = marker_cells(0)
    assert cells.shape == (6, 6) and cells[0].all() and cells[:, 0].all()  # the black border
    pts, dark = junctions(0)
    assert len(pts) == 3
    # every junction sits on the cell grid (1.6 cm cells of a 9.6 cm marker), inside the border
    grid = (pts + 4.8) / 1.6
    assert np.allclose(grid, np.round(grid)) and (grid >= 2 - 1e-9).all() and (grid <= 4 + 1e-9).all()
    for (x, y), d in zip(pts, dark):
        j, i = int(round((x + 4.8) / 1.6)), int(round((4.8 - y) / 1.6))
        q = cells[i - 1:i + 1, j - 1:j + 1]
        assert q[0, 0] == q[1, 1] == d and q[0, 1] == q[1, 0] == (not d)


def test_shift_corners_moves_each_corner_along_its_bisector():
    sq = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
    assert np.allclose(shift_corners(sq, 1.0), [[-1, -1], [11, -1], [11, 11], [-1, 11]])
    assert np.allclose(shift_corners(shift_corners(sq, 0.7), -0.7), sq)


@pytest.mark.parametrize("erode", [0.0, 0.8])
def test_edge_shift_is_measured_and_taken_back(erode):
    """Black print eroded by a known amount: the detected corners lie inward by about that much; the junctions
    measure it and the corrected corners are back where the marker is."""
    img = draw_marker(0, CORNERS, erode)
    det = markers_in_image(img)
    assert set(det) == {0}
    raw = det[0]
    shift = edge_shift_px(img, 0, raw)
    assert shift is not None and abs(shift - erode) < 0.25, shift
    fixed = shift_corners(raw, shift)
    assert np.abs(fixed - CORNERS).max() < 0.35
    if erode:
        assert np.abs(raw - CORNERS).max() > 0.7  # without the correction the corners are off


def test_junctions_hidden_by_an_occluder_are_not_used():
    img = draw_marker(0, CORNERS, 0.8)
    raw = markers_in_image(img)[0]
    hidden = img.copy()
    hidden[180:300, 180:300] = 200  # a pale object over the marker's middle: no junction is seen there
    assert edge_shift_px(hidden, 0, raw) is None


def test_markers_file_roundtrip(tmp_path):
    m = Markers(frames={"frame_00000.png": {0: CORNERS.copy()}}, edge_shift_px=0.4, shift_samples=5,
                names=["frame_00000.png", "frame_00001.png"])
    write_markers(tmp_path / "markers.json", m, CubeSpec())
    back = read_markers(tmp_path / "markers.json")
    assert back.names == m.names and back.edge_shift_px == 0.4 and back.shift_samples == 5
    assert np.allclose(back.frames["frame_00000.png"][0], CORNERS, atol=1e-4)
    other = CubeSpec(size=12.0, marker_size=11.0, dictionary="DICT_5X5_50", face_ids=(6, 7, 8, 9, 10, 11))
    write_markers(tmp_path / "other.json", m, other)
    from plantsplat.markers import recorded_cube

    assert recorded_cube(tmp_path / "other.json") == other and CubeSpec.from_record(CubeSpec().record()) == CubeSpec()
    (tmp_path / "bad.json").write_text('{"frames": 3}')
    from plantsplat.errors import PlantsplatError

    with pytest.raises(PlantsplatError, match="not a markers file"):
        read_markers(tmp_path / "bad.json")


def test_frames_detected_in_threads_give_what_one_thread_gives(tmp_path, monkeypatch):
    """The frames are read and detected in a thread pool (issue 43): every frame keeps its own markers, frames without
    one are left out, and the edge shift is the one a single thread measures."""
    names = []
    for k in range(7):
        name = f"frame_{k:05d}.png"
        img = draw_marker(k % 3, CORNERS + 6.0 * k, 0.6) if k != 4 else np.full((480, 480), 128, np.uint8)
        cv2.imwrite(str(tmp_path / name), img)
        names.append(name)
    import plantsplat.resources

    found = {}
    for threads in (1, 2):
        monkeypatch.setattr(plantsplat.resources, "usable_cores", lambda n=threads: n)  # the pool's threads
        found[threads] = detect_frames(tmp_path, names)
    one, two = found[1], found[2]
    assert list(two.frames) == [n for n in names if n != "frame_00004.png"] and two.names == names
    assert two.shift_samples == one.shift_samples == 6 and two.edge_shift_px == one.edge_shift_px
    assert abs(two.edge_shift_px - 0.6) < 0.25
    for k, n in enumerate(names):
        if n in two.frames:
            assert set(two.frames[n]) == {k % 3} and np.array_equal(two.frames[n][k % 3], one.frames[n][k % 3])
            assert np.abs(two.frames[n][k % 3] - (CORNERS + 6.0 * k)).max() < 0.35


def _marker_frames(ws, count: int) -> list[str]:
    """``count`` frames in ``ws``'s images folder, each showing one marker but the fifth."""
    ws.images_dir.mkdir(parents=True)
    names = []
    for k in range(count):
        name = f"frame_{k:05d}.png"
        img = draw_marker(k % 3, CORNERS + 6.0 * k, 0.6) if k != 4 else np.full((480, 480), 128, np.uint8)
        cv2.imwrite(str(ws.images_dir / name), img)
        names.append(name)
    return names


def test_markers_found_beside_the_stage_are_those_found_in_it(tmp_path):
    """The poses stage detects the markers in a process of its own at the lowest priority, beside structure from
    motion (issue 43): the same corners to the last bit, the same ``markers.json``, and its folder gone after."""
    from plantsplat.poses import PosesConfig
    from plantsplat.poses.stage import MARKERS_DIR, detect_markers, finish_markers, start_markers
    from plantsplat.workspace import Workspace

    ws = Workspace(tmp_path / "ws")
    names = _marker_frames(ws, 6)
    cube = CubeSpec()
    here, there = {"timings": {}}, {"timings": {}}
    mine = detect_markers(ws, names, cube, PosesConfig(), here)
    written = ws.markers_json.read_bytes()
    ws.markers_json.unlink()
    theirs = finish_markers(ws, start_markers(ws, names, cube), cube, there)
    assert ws.markers_json.read_bytes() == written and theirs.names == names
    assert list(theirs.frames) == list(mine.frames) and theirs.edge_shift_px == mine.edge_shift_px
    assert all(np.array_equal(theirs.frames[n][m], c) for n, d in mine.frames.items() for m, c in d.items())
    assert there["frames_with_markers"] == here["frames_with_markers"] == 5 and there["timings"]["detect_markers_s"] > 0
    assert not (ws.root / ".plantsplat" / "colmap" / MARKERS_DIR).exists()


def test_a_frame_the_marker_process_cannot_read_stops_the_stage_with_its_own_line(tmp_path):
    """A broken frame ends the marker process; the stage gives that frame's one-line error, not the process's."""
    from plantsplat.errors import PlantsplatError
    from plantsplat.poses.stage import finish_markers, start_markers
    from plantsplat.workspace import Workspace

    ws = Workspace(tmp_path / "ws")
    names = _marker_frames(ws, 3)
    (ws.images_dir / names[1]).write_bytes(b"not a png")
    with pytest.raises(PlantsplatError, match=r"frame_00001\.png: unreadable or not an image") as err:
        finish_markers(ws, start_markers(ws, names, CubeSpec()), CubeSpec(), {"timings": {}})
    assert err.value.exit_code == 1 and "\n" not in str(err.value)

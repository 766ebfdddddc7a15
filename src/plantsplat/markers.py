"""The calibration cube's ArUco markers in every frame, detected once per workspace (``WS/markers.json``).

The poses stage detects them (:func:`detect_frames`) and writes ``markers.json``; every later user
(calibration, segmentation) reads that file instead of detecting again.

Corners are located with OpenCV's AprilTag refinement (it fits the marker's edges with lines). An edge
between black print and white card is still found slightly off where blur, noise reduction or tone
mapping widen the white: on three independent renders the markers came out 0.4-1.1 % too small, and
the cube's scale as much too large. The pattern's X-junctions (where two black and two white cells
meet diagonally) do not move under such blur, so each detection's corners and junctions together
give the edge shift in pixels (:func:`edge_shift_px`); the capture's median shift is taken back off
every detection's corners (:func:`shift_corners`).

Example:
    >>> import numpy as np
    >>> square = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
    >>> shift_corners(square, 1.0).round(3).tolist()   # a 10 px square grown by 1 px on every side
    [[-1.0, -1.0], [11.0, -1.0], [11.0, 11.0], [-1.0, 11.0]]
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import least_squares

from plantsplat.cube import CubeSpec
from plantsplat.errors import PlantsplatError
from plantsplat.io import read_image, read_json, write_json_atomic
from plantsplat.log import get_logger
from plantsplat.resources import map_on_cores

log = get_logger(__name__)

MARKERS_VERSION = 1
APRILTAG_OFFSET_PX = 0.5
"""Where OpenCV's AprilTag corner refinement puts pixel centres (see :func:`markers_in_image`)."""
MIN_SHIFT_SAMPLES = 3
"""Detections with junctions needed before the capture's edge shift is taken off (fewer: no correction)."""


def markers_in_image(image: np.ndarray, cube: CubeSpec = CubeSpec()) -> dict[int, np.ndarray]:
    """The cube's markers in an RGB or gray uint8 image: ``{marker_id: corners [4, 2]}`` (pixels, ArUco order).

    Pixel centres are at integer coordinates (OpenCV's convention). OpenCV's AprilTag refinement
    reports corners half a pixel further right and down (it counts from the pixel's corner): on 76
    markers of real-size captures its corners lay a median 0.45 px right and 0.45 px below those of
    ``cornerSubPix`` refinement, and a fitted synthetic marker shows the same; that half pixel is taken
    off. Corners are otherwise as detected (see :func:`shift_corners` for the edge-shift correction).
    """
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_APRILTAG
    detector = cv2.aruco.ArucoDetector(cube.aruco_dictionary(), params)
    corners, ids, _ = detector.detectMarkers(gray)
    out: dict[int, np.ndarray] = {}
    if ids is None:
        return out
    for c, i in zip(corners, ids.ravel()):
        if cube.face_of(int(i)) is not None:
            out[int(i)] = np.asarray(c, dtype=np.float64).reshape(4, 2) - APRILTAG_OFFSET_PX
    return out


def marker_cells(marker_id: int, cube: CubeSpec = CubeSpec()) -> np.ndarray:
    """The printed marker as cells, border included: ``[n, n]`` bool, True = black, row 0 at the marker's top."""
    n = cube.aruco_dictionary().markerSize + 2
    img = cv2.aruco.generateImageMarker(cube.aruco_dictionary(), int(marker_id), n, borderBits=1)
    return img < 128


def junctions(marker_id: int, cube: CubeSpec = CubeSpec()) -> tuple[np.ndarray, np.ndarray]:
    """X-junctions of a marker's print: ``(points [J, 2], dark_first [J])``.

    Points are in the marker's plane (cm, origin at its centre, x to its right, y to its top); a junction
    is a grid point whose four cells are black and white in diagonal pairs. ``dark_first`` says whether
    its top-left and bottom-right cells are the black ones.
    """
    cells = marker_cells(marker_id, cube)
    n = cells.shape[0]
    step = cube.marker_size / n
    pts, dark = [], []
    for i in range(1, n):
        for j in range(1, n):
            q = cells[i - 1:i + 1, j - 1:j + 1]
            if q[0, 0] == q[1, 1] and q[0, 1] == q[1, 0] and q[0, 0] != q[0, 1]:
                pts.append((-cube.marker_size / 2 + j * step, cube.marker_size / 2 - i * step))
                dark.append(bool(q[0, 0]))
    return np.array(pts, dtype=np.float64).reshape(-1, 2), np.array(dark, dtype=bool)


def _square(cube: CubeSpec) -> np.ndarray:
    """The marker's corners in its plane (cm), ArUco order. ``[4, 2]``"""
    h = cube.marker_size / 2
    return np.array([[-h, h], [h, h], [h, -h], [-h, -h]])


def _apply(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    q = np.c_[pts, np.ones(len(pts))] @ H.T
    return q[:, :2] / q[:, 2:]


def inward_bisectors(corners: np.ndarray) -> np.ndarray:
    """Per corner of a convex quad ``[4, 2]``: how far it moves when every edge moves inward by one pixel. ``[4, 2]``

    Along the bisector of its two edges, ``1 / sin(angle / 2)`` pixels.
    """
    out = np.zeros((4, 2))
    for k in range(4):
        a = corners[(k + 1) % 4] - corners[k]
        b = corners[(k - 1) % 4] - corners[k]
        a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
        half = 0.5 * np.arccos(np.clip(a @ b, -1.0, 1.0))
        out[k] = (a + b) / max(np.linalg.norm(a + b), 1e-12) / max(np.sin(half), 1e-6)
    return out


def shift_corners(corners: np.ndarray, shift_px: float) -> np.ndarray:
    """Corners ``[4, 2]`` of a marker whose edges were all found ``shift_px`` pixels inward, moved back out."""
    corners = np.asarray(corners, dtype=np.float64)
    return corners - shift_px * inward_bisectors(corners)


def _refined_junctions(gray: np.ndarray, H: np.ndarray, pts: np.ndarray, dark: np.ndarray, cell_cm: float,
                       cell_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Junctions predicted by the homography ``H`` (marker plane -> pixels) and refined by ``cv2.cornerSubPix``.

    A junction is kept when it moved less than a third of a cell and its four cells show the printed
    dark and bright diagonals (occluded or washed-out junctions do not). Returns
    ``(plane points [J, 2], pixels [J, 2])``.
    """
    guess = _apply(H, pts)
    win = max(2, int(round(cell_px / 4)))
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 0.01)
    found = cv2.cornerSubPix(gray, guess.astype(np.float32).reshape(-1, 1, 2).copy(), (win, win), (-1, -1), crit)
    found = found.reshape(-1, 2).astype(np.float64)
    keep = np.linalg.norm(found - guess, axis=1) < cell_px / 3
    h, w = gray.shape
    half = cell_cm / 2
    around = np.array([[-half, half], [half, half], [half, -half], [-half, -half]])  # TL, TR, BR, BL cell centres
    for j in np.flatnonzero(keep):
        uv = np.round(_apply(H, pts[j] + around)).astype(int)
        if (uv < 0).any() or (uv[:, 0] >= w).any() or (uv[:, 1] >= h).any():
            keep[j] = False
            continue
        v = gray[uv[:, 1], uv[:, 0]]
        black, white = ([0, 2], [1, 3]) if dark[j] else ([1, 3], [0, 2])
        keep[j] = v[black].max() < v[white].min()
    return pts[keep], found[keep]


def edge_shift_px(gray: np.ndarray, marker_id: int, corners: np.ndarray, cube: CubeSpec = CubeSpec()) -> float | None:
    """How far inward (pixels) the detected edges of one marker lie, from its X-junctions; None without any.

    A homography (marker plane -> image) and one edge shift are fitted together: the junctions at their
    printed places, the corners moved inward by the shift along their bisectors (:func:`inward_bisectors`).
    ``gray``: the frame as float32 or uint8 ``[H, W]``.
    """
    pts, dark = junctions(marker_id, cube)
    if not len(pts):
        return None
    corners = np.asarray(corners, dtype=np.float64)
    square = _square(cube)
    H = cv2.getPerspectiveTransform(square.astype(np.float32), corners.astype(np.float32)).astype(np.float64)
    n = cube.aruco_dictionary().markerSize + 2
    cell_px = float(np.mean(np.linalg.norm(corners - np.roll(corners, 1, axis=0), axis=1))) / n
    pts, seen = _refined_junctions(np.asarray(gray, dtype=np.float32), H, pts, dark, cube.marker_size / n, cell_px)
    if not len(pts):
        return None

    def residuals(x):
        Hx = np.append(x[:8], 1.0).reshape(3, 3)
        c = _apply(Hx, square)
        return np.r_[(c + x[8] * inward_bisectors(c) - corners).ravel(), (_apply(Hx, pts) - seen).ravel()]

    fit = least_squares(residuals, np.r_[(H / H[2, 2]).ravel()[:8], 0.0])
    return float(fit.x[8]) if fit.success and np.isfinite(fit.x[8]) else None


@dataclass
class Markers:
    """The markers of a capture: ``frames`` maps a frame's name to ``{marker_id: corners [4, 2]}`` (corrected)."""

    frames: dict[str, dict[int, np.ndarray]] = field(default_factory=dict)
    edge_shift_px: float = 0.0
    """The edge shift taken off every detection (the median of :attr:`shift_samples`; 0 with too few)."""
    shift_samples: int = 0
    """Detections whose X-junctions measured the edge shift."""
    names: list[str] = field(default_factory=list)
    """Every frame searched, with markers or without."""


def _detect_one(path: Path, cube: CubeSpec) -> tuple[dict[int, np.ndarray], list[float]]:
    """One frame's markers and the edge shifts measured on them."""
    gray = read_image(path, mode="gray")
    det = markers_in_image(gray, cube)
    shifts = [edge_shift_px(gray, mid, c, cube) for mid, c in det.items()]
    return det, [s for s in shifts if s is not None]


def detect_frames(image_dir: Path, names: list[str], cube: CubeSpec = CubeSpec()) -> Markers:
    """Detect the cube's markers in every frame and correct the capture's edge shift (see the module docstring).

    Frames are read and detected in a thread pool (OpenCV releases the GIL); results are taken in frame order, so
    the outcome does not depend on the number of threads."""
    raw: dict[str, dict[int, np.ndarray]] = {}
    shifts: list[float] = []
    found = map_on_cores(lambda n: _detect_one(Path(image_dir) / n, cube), names, "detecting the cube's markers")
    for name, (det, s) in zip(names, found):
        if det:
            raw[name] = det
            shifts.extend(s)
    shift = float(np.median(shifts)) if len(shifts) >= MIN_SHIFT_SAMPLES else 0.0
    frames = {n: {m: shift_corners(c, shift) for m, c in d.items()} for n, d in raw.items()}
    markers = Markers(frames=frames, edge_shift_px=shift, shift_samples=len(shifts), names=list(names))
    log_found(markers)
    return markers


def log_found(markers: Markers) -> None:
    """Say in how many frames the markers were found, and the edge shift."""
    log.info("markers: found in %d of %d frames; edge shift %.2f px (from %d detections)", len(markers.frames),
             len(markers.names), markers.edge_shift_px, markers.shift_samples)


def write_markers(path: Path, markers: Markers, cube: CubeSpec) -> None:
    """``markers.json``: the cube, the edge shift and every frame's corrected corners."""
    write_json_atomic(path, {
        "version": MARKERS_VERSION,
        "cube": cube.record(),
        "edge_shift_px": markers.edge_shift_px,
        "shift_samples": markers.shift_samples,
        "names": markers.names,
        "frames": {n: {str(m): np.round(c, 4).tolist() for m, c in d.items()} for n, d in markers.frames.items()},
    })


def recorded_cube(path: Path) -> CubeSpec | None:
    """The cube as the poses stage recorded it in ``markers.json`` (its ``--cube-size``, ``--marker-size``,
    dictionary and ids), or None when there is no record: the one source of the cube's geometry for the
    stages and checks after poses."""
    path = Path(path)
    if not path.is_file():
        return None
    c = read_json(path).get("cube")
    if c is None:
        return None
    try:
        return CubeSpec.from_record(c)
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise PlantsplatError(f"{path}: the cube's record is unreadable ({exc}); re-run `plantsplat poses`") from exc


def read_markers(path: Path) -> Markers:
    """Read ``markers.json`` (a clear error when it is corrupt)."""
    data = read_json(path)
    try:
        frames = {n: {int(m): np.asarray(c, dtype=np.float64).reshape(4, 2) for m, c in d.items()}
                  for n, d in data["frames"].items()}
        return Markers(frames=frames, edge_shift_px=float(data["edge_shift_px"]),
                       shift_samples=int(data.get("shift_samples", 0)), names=list(data.get("names", [])))
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise PlantsplatError(f"{path}: not a markers file ({exc}); delete it and re-run `plantsplat poses`") from exc

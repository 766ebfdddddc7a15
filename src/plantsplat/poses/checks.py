"""Checks of a registered model against what the capture itself says.

Each check has a name, a measured value and the threshold it is held to (:class:`plantsplat.checks.Check`);
the poses stage records them all in ``poses.json`` and fails when one that matters fails. What they look at:

- the camera's path through video time (:func:`path_deviations`, :func:`off_path`): a phone moves
  smoothly around the plant, so each camera must lie where its video neighbours put it on their
  orbit. Deviations are measured in units of the neighbours' own spacing (position) and turn
  (rotation), so no unit or scene size enters;
- the cube: its markers must reproject where they are detected (the calibration's residuals), two
  halves of the video must give the same scale, and the SfM points on the cube's faces must lie on
  the faces' planes (:func:`face_offsets`).

Example:
    >>> import numpy as np
    >>> def looking_at_origin(a):  # a camera 50 cm out at angle a, its optical axis (z) through the origin
    ...     M = np.eye(4); z = -np.array([np.cos(a), np.sin(a), 0.0]); x = np.cross(z, [0, 0, 1.0])
    ...     M[:3, :3] = np.stack([x, np.cross(z, x), z], 1); M[:3, 3] = -50 * z; return M
    >>> (np.round(orbit_centre([looking_at_origin(a) for a in (0.0, 2.0, 4.0)]), 6) + 0.0).tolist()
    [0.0, 0.0, 0.0]
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from plantsplat.cube import FACE_NAMES
from plantsplat.log import get_logger

log = get_logger(__name__)


def _rotvec(R: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(R).as_rotvec()


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(_rotvec(R))))


def orbit_centre(c2w: list[np.ndarray]) -> np.ndarray | None:
    """The point closest (least squares) to every camera's optical axis: what the cameras circle. ``[3]``

    ``c2w``: camera-to-world poses (OpenCV axes: the optical axis is the third column). None when the
    axes are (nearly) parallel.
    """
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for M in c2w:
        d = M[:3, 2] / np.linalg.norm(M[:3, 2])
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ M[:3, 3]
    if len(c2w) < 3 or np.linalg.cond(A) > 1e8:
        return None
    return np.linalg.solve(A, b)


def _predict(c2w: dict, a: str, b: str, ta: float, tb: float, t: float,
             centre: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Pose at time ``t`` from the poses of frames ``a`` (time ``ta``) and ``b`` (``tb``), inter- or extrapolated.

    The camera is moved as it moves around an orbit: its rotation turns at a constant rate and the
    orbit's ``centre``, seen from the camera, moves linearly; so a gap of several frames is bridged
    along the arc, not its chord (straight lines without a centre). Returns ``(centre of the camera [3],
    rotation [3, 3], spacing of a and b, their turn in degrees)``.
    """
    f = (t - ta) / (tb - ta)
    Ca, Cb = c2w[a][:3, 3], c2w[b][:3, 3]
    Ra, Rb = c2w[a][:3, :3], c2w[b][:3, :3]
    rel = _rotvec(Ra.T @ Rb)
    R = Ra @ Rotation.from_rotvec(f * rel).as_matrix()
    if centre is None:
        C = Ca + f * (Cb - Ca)
    else:
        oa, ob = Ra.T @ (centre - Ca), Rb.T @ (centre - Cb)  # the orbit's centre in each camera
        C = centre - R @ (oa + f * (ob - oa))
    return C, R, float(np.linalg.norm(Cb - Ca)), float(np.degrees(np.linalg.norm(rel)))


def _bend(c2w: dict, trio: list[tuple[str, float]], a: tuple[str, float], b: tuple[str, float], t: float
          ) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Pose at time ``t`` from three frames ``trio`` (``(name, time)``) around it: the camera's centre on the parabola
    through theirs in time (a path that bends or climbs between two rings, as it does where the camera rises to the
    next ring), its rotation turned from ``a`` to ``b``, the two of them on either side of ``t``. Returns what
    :func:`_predict` does."""
    ts = [tk for _, tk in trio]
    C = sum(np.prod([(t - tj) / (ti - tj) for j, tj in enumerate(ts) if j != i]) * c2w[n][:3, 3]
            for i, (n, ti) in enumerate(trio))
    _, R, spacing, turn = _predict(c2w, a[0], b[0], a[1], b[1], t, None)
    return C, R, spacing, turn


def _path_errors(c2w: dict[str, np.ndarray], names: list[str], times: list[float]) -> dict[str, list[tuple]]:
    """Per registered frame, for each way its video neighbours predict it: ``(centre error, centre step,
    rotation error in degrees, rotation step in degrees)``; the steps are the motion from the nearer neighbour.
    The ways: between its two neighbours (:func:`_predict`), from the two on either side, and where it has them,
    through three neighbours around it (:func:`_bend`)."""
    reg = [(n, t) for n, t in zip(names, times) if n in c2w]
    centre = orbit_centre([c2w[n] for n, _ in reg])
    out: dict[str, list[tuple]] = {}
    for k, (n, t) in enumerate(reg):
        options = []
        if 0 < k < len(reg) - 1:
            options.append((reg[k - 1], reg[k + 1], None))
            options += [(reg[k - 1], reg[k + 1], [reg[i] for i in trio]) for trio in ((k - 2, k - 1, k + 1),
                        (k - 1, k + 1, k + 2)) if min(trio) >= 0 and max(trio) < len(reg)]
        if k >= 2:
            options.append((reg[k - 2], reg[k - 1], None))
        if k + 2 < len(reg):
            options.append((reg[k + 1], reg[k + 2], None))
        rows = []
        for (a, ta), (b, tb), trio in options:
            C, R, spacing, turn = (_predict(c2w, a, b, ta, tb, t, centre) if trio is None
                                   else _bend(c2w, trio, (a, ta), (b, tb), t))
            near = min(abs(t - ta), abs(t - tb)) / max(abs(tb - ta), 1e-9)
            rows.append((float(np.linalg.norm(c2w[n][:3, 3] - C)), spacing * near,
                         _angle_deg(R.T @ c2w[n][:3, :3]), turn * near))
        if rows:
            out[n] = rows
    return out


def path_deviations(c2w: dict[str, np.ndarray], names: list[str], times: list[float],
                    min_turn_deg: float = 1.0, jitter: float = 3.0, turn_slack: float = 2.0) -> dict[str, float]:
    """How far each camera lies from the path of its video neighbours, in units of the step to them.

    ``c2w``: camera-to-world poses of the registered frames; ``names`` in video order with ``times``
    (source frame numbers, or positions). Each frame is predicted from its nearest registered frames
    on either side (interpolation), or from the two nearest on one side (extrapolation), moving along
    their orbit (:func:`_predict`), or through three around it where the path bends (:func:`_bend`); the
    best agreeing prediction counts, so the first frame of a new ring, a step away from the last, is
    judged by the frames after it. A frame's deviation is the
    larger of its centre's distance from the prediction over the step from its nearer neighbour
    (their spacing, pro rata of time) and its rotation's angle from the prediction over that step's
    turn, divided by ``turn_slack``: a hand-held phone (or a scanner's head) turns less evenly than it
    moves, while a wrongly posed frame is off in both. A hand-held camera also shakes: a step is taken
    as at least ``jitter`` times the capture's median error (centre and rotation apart; and at least
    ``min_turn_deg``), so slow steps do not make the shake look large. Frames with fewer than two
    registered neighbours are not judged.
    """
    errors = _path_errors(c2w, names, times)
    if not errors:
        return {}

    def dev(dc, sc, dr, sr, floor_c=0.0, floor_r=min_turn_deg):
        return max(dc / max(sc, floor_c, 1e-12), dr / max(sr, floor_r) / turn_slack)

    best = [min(rows, key=lambda r: dev(*r)) for rows in errors.values()]
    floor_c = jitter * float(np.median([r[0] for r in best]))
    floor_r = max(min_turn_deg, jitter * float(np.median([r[2] for r in best])))
    return {n: min(dev(*r, floor_c, floor_r) for r in rows) for n, rows in errors.items()}


def off_path(c2w: dict[str, np.ndarray], names: list[str], times: list[float], limit: float,
             max_share: float) -> list[str]:
    """Frames whose camera leaves the path through its video neighbours by more than ``limit`` (see
    :func:`path_deviations`), worst first and judged again without it, up to ``max_share`` of the frames."""
    c2w = dict(c2w)
    dropped: list[str] = []
    while len(dropped) < max_share * len(names):
        dev = path_deviations(c2w, names, times)
        if not dev:
            break
        worst = max(dev, key=dev.get)
        if dev[worst] <= limit:
            break
        dropped.append(worst)
        del c2w[worst]
    return dropped


def _run_deviation(c2w: dict, run: list[tuple[str, float]], a: tuple[str, float], b: tuple[str, float],
                   centre: np.ndarray | None) -> float:
    """The smallest deviation of the frames of ``run`` from their poses predicted from frames ``a`` and ``b``
    (``(name, time)``), in units of the spacing (position) and twice the turn (rotation) of ``a`` and ``b``."""
    devs = []
    for n, t in run:
        C, R, spacing, turn = _predict(c2w, a[0], b[0], a[1], b[1], t, centre)
        devs.append(max(float(np.linalg.norm(c2w[n][:3, 3] - C)) / max(spacing, 1e-12),
                        _angle_deg(R.T @ c2w[n][:3, :3]) / max(turn, 1.0) / 2.0))
    return min(devs)


def off_path_runs(c2w: dict[str, np.ndarray], names: list[str], times: list[float], limit: float,
                  max_run: int = 4) -> list[str]:
    """Runs of up to ``max_run`` consecutive registered frames that agree with each other but not with the path
    of the frames around them (a short stretch posed as a block somewhere else, which :func:`off_path`
    cannot see: each of its frames is predicted well from the others).

    A run is predicted along the orbit (:func:`_predict`) from the registered frames just before and
    just after it, and from the two before it and the two after it; it is off when, for each of those
    predictions, every frame of it deviates by more than ``limit`` of the two frames' spacing (position) or
    of twice their turn (rotation). A run that starts a new ring agrees with the frames after it, so it
    stays. Longer runs are judged first.
    """
    reg = [(n, t) for n, t in zip(names, times) if n in c2w]
    centre = orbit_centre([c2w[n] for n, _ in reg])
    dropped: set[str] = set()
    for k in range(max_run, 0, -1):  # a run that holds a right frame is not off: longer runs first
        keep = [r for r in reg if r[0] not in dropped]
        # a run whose first frame agrees with the two frames before it is not off (its deviation is the smallest of
        # its frames'), so only runs that start with a jump are judged in full: the same answer, in linear time
        starts = [i for i in range(2, len(keep) - k - 1)
                  if _run_deviation(c2w, [keep[i]], keep[i - 2], keep[i - 1], centre) > limit]
        for i in starts:
            run = keep[i:i + k]
            sides = [(keep[i - 1], keep[i + k]), (keep[i - 2], keep[i - 1]), (keep[i + k], keep[i + k + 1])]
            if min(_run_deviation(c2w, run, a, b, centre) for a, b in sides) > limit:
                dropped.update(n for n, _ in run)
    return [n for n, _ in reg if n in dropped]


def facing_away(c2w: dict[str, np.ndarray], max_angle_deg: float) -> list[str]:
    """Cameras whose optical axis turns more than ``max_angle_deg`` away from the point every camera looks at
    (:func:`orbit_centre`): on an orbit around a plant no camera looks away from it. ``c2w``: camera-to-world
    poses (OpenCV axes)."""
    centre = orbit_centre(list(c2w.values()))
    if centre is None:
        return []
    out = []
    for n, M in c2w.items():
        to_centre = centre - M[:3, 3]
        cos = float(M[:3, 2] @ to_centre / max(np.linalg.norm(to_centre), 1e-12))
        if cos < np.cos(np.radians(max_angle_deg)):
            out.append(n)
    return out


def face_offsets(points: np.ndarray, cube, band: float, margin: float,
                 min_points: int) -> dict[str, tuple[float, int]]:
    """Where SfM points near each face of the cube lie, along the face's normal (cube frame, cm).

    Points within ``band`` cm of a face's plane and at least ``margin`` cm inside its edges (a
    silhouette's points are not on the face) are kept; for each face with ``min_points`` of them the
    result is ``(median signed distance from the plane, count)``. On a right model the medians are
    near 0; a wrong scale or pose of the cube moves whole faces.
    """
    out = {}
    for face in FACE_NAMES:
        if face == "bottom":
            continue
        c, n, r, u = cube.face_frame(face)
        d = (points - c) @ n  # [P]
        inside = np.maximum(np.abs((points - c) @ r), np.abs((points - c) @ u)) < cube.size / 2 - margin
        on = (np.abs(d) < band) & inside
        if on.sum() >= min_points:
            out[face] = (float(np.median(d[on])), int(on.sum()))
    return out

"""The 10 cm ArUco calibration cube: geometry and pose (detection: :mod:`plantsplat.markers`).

Cube frame (used by ``plantsplat synth``, segmentation and metric calibration alike): origin at the
centre of the bottom face, i.e. on the ground plane under the cube, +z up, edges along x and y,
centimetres. Each face carries one marker, centred, of side ``marker_size`` (9.6 cm on a 10 cm cube),
with these ids by default:

=====  ======  ==================================  ========================
face   normal  marker "up" (top edge direction)    default id
=====  ======  ==================================  ========================
+x     +x      +z                                  0
-x     -x      +z                                  1
+y     +y      +z                                  2
-y     -y      +z                                  3
top    +z      +y                                  4
bottom -z      +y                                  5
=====  ======  ==================================  ========================

Looking at a face from outside, the marker's "right" is ``up x normal``. Corners are listed in
OpenCV ArUco order (top-left, top-right, bottom-right, bottom-left as the marker is printed).

Example:
    >>> cube = CubeSpec()
    >>> cube.marker_corners(4)[0].tolist()   # top-left corner of the top marker
    [-4.8, 4.8, 10.0]
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

FACE_NAMES = ("+x", "-x", "+y", "-y", "top", "bottom")
_NORMALS = {
    "+x": (1, 0, 0),
    "-x": (-1, 0, 0),
    "+y": (0, 1, 0),
    "-y": (0, -1, 0),
    "top": (0, 0, 1),
    "bottom": (0, 0, -1),
}
_UPS = {"+x": (0, 0, 1), "-x": (0, 0, 1), "+y": (0, 0, 1), "-y": (0, 0, 1), "top": (0, 1, 0), "bottom": (0, 1, 0)}


@dataclass(frozen=True)
class CubeSpec:
    """A marker cube: edge length, marker side, ArUco dictionary and the marker id on each face."""

    size: float = 10.0
    """Cube edge length (cm)."""
    marker_size: float = 9.6
    """Side of each printed marker, black border included (cm)."""
    dictionary: str = "DICT_4X4_50"
    """OpenCV predefined ArUco dictionary name."""
    face_ids: tuple[int, ...] = (0, 1, 2, 3, 4, 5)
    """Marker ids on the faces +x, -x, +y, -y, top, bottom."""
    _by_id: dict = field(default_factory=dict, init=False, repr=False, compare=False)
    _frames: dict = field(default_factory=dict, init=False, repr=False, compare=False)  # face -> face_frame()

    def __post_init__(self):
        if len(self.face_ids) != 6 or len(set(self.face_ids)) != 6:
            raise ValueError("face_ids must name 6 distinct marker ids")
        if not 0 < self.marker_size <= self.size:
            raise ValueError("marker_size must be positive and at most the cube size")
        self._by_id.update({mid: FACE_NAMES[i] for i, mid in enumerate(self.face_ids)})

    def face_of(self, marker_id: int) -> str | None:
        return self._by_id.get(int(marker_id))

    def face_frame(self, face: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(centre, normal, right, up)`` of a face in the cube frame (fresh arrays; computed once per face:
        the cube pose solver asks for them thousands of times per capture)."""
        if face not in self._frames:
            n = np.array(_NORMALS[face], dtype=np.float64)
            up = np.array(_UPS[face], dtype=np.float64)
            right = np.cross(up, n)
            centre = np.array([0.0, 0.0, self.size / 2]) + n * self.size / 2
            self._frames[face] = (centre, n, right, up)
        return tuple(a.copy() for a in self._frames[face])

    def marker_corners(self, marker_id: int) -> np.ndarray:
        """The 4 corners of a marker in the cube frame, ArUco order. ``[4, 3]``."""
        face = self.face_of(marker_id)
        if face is None:
            raise KeyError(f"marker id {marker_id} is not on this cube (ids {list(self.face_ids)})")
        c, _, r, u = self.face_frame(face)
        h = self.marker_size / 2
        return np.stack([c - r * h + u * h, c + r * h + u * h, c + r * h - u * h, c - r * h - u * h])

    def corners(self) -> np.ndarray:
        """The cube's 8 vertices in the cube frame. ``[8, 3]``."""
        h = self.size / 2
        return np.array([[x, y, z] for z in (0.0, self.size) for y in (-h, h) for x in (-h, h)])

    def faces(self) -> list[list[int]]:
        """Vertex indices (into :meth:`corners`) of the 6 faces, counter-clockwise seen from outside."""
        return [[1, 3, 7, 5], [0, 4, 6, 2], [2, 6, 7, 3], [0, 1, 5, 4], [4, 5, 7, 6], [0, 2, 3, 1]]

    def record(self) -> dict:
        """The cube's own fields as plain values (``markers.json``'s ``cube``); :meth:`from_record` reads them back."""
        return {"size": self.size, "marker_size": self.marker_size, "dictionary": self.dictionary,
                "face_ids": list(self.face_ids)}

    @classmethod
    def from_record(cls, c: dict) -> CubeSpec:
        """The cube of a :meth:`record` (the dictionary and ids default to the standard cube's where absent)."""
        return cls(size=float(c["size"]), marker_size=float(c["marker_size"]),
                   dictionary=str(c.get("dictionary", cls.dictionary)),
                   face_ids=tuple(int(i) for i in c.get("face_ids", cls.face_ids)))

    def aruco_dictionary(self):
        import cv2  # deferred: OpenCV is slow to load, and the CLI imports this module (for CubeSpec)

        if not hasattr(cv2.aruco, self.dictionary):
            raise ValueError(f"unknown ArUco dictionary {self.dictionary!r}")
        return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))


def in_cube_box(points: np.ndarray, size: float, margin: float) -> np.ndarray:
    """``[N]`` bool: points ``[N, 3]`` (cube frame) inside the box of a cube of edge ``size`` standing on the ground
    at the origin, grown by ``margin`` on every side.

    Example:
        >>> in_cube_box(np.array([[0.0, 0.0, 5.0], [5.3, 0.0, 1.0], [0.0, 0.0, -1.0]]), 10.0, 0.5).tolist()
        [True, True, False]
    """
    h = size / 2 + margin
    return ((np.abs(points[:, 0]) < h) & (np.abs(points[:, 1]) < h)
            & (points[:, 2] > -margin) & (points[:, 2] < size + margin))


def cube_box_distance(points: np.ndarray, size: float) -> np.ndarray:
    """``[N]`` distance of points ``[N, 3]`` (cube frame) from the box of a cube of edge ``size`` standing on the
    ground at the origin, 0 inside it.

    The segment stage judges by it whether a Gaussian stands before the cube or draws its face: on a close-up of
    foreign render 103 (2026-11-29), 20 Gaussians 0.1-0.5 cm off a face seen at a slant lay 0.5-1.4 cm nearer than the
    face along the rays, and judged by depth alone they hid 4,064 of the cube's 42,362 pixels.

    Example:
        >>> cube_box_distance(np.array([[0.0, 5.4, 5.0], [8.0, 9.0, 10.0], [1.0, 1.0, 1.0]]), 10.0).round(6).tolist()
        [0.4, 5.0, 0.0]
    """
    out = np.maximum(np.abs(points[:, :2]) - size / 2, 0.0)
    above = np.maximum(np.maximum(points[:, 2] - size, -points[:, 2]), 0.0)
    return np.sqrt((out ** 2).sum(axis=1) + above ** 2)


def cube_pose(
    detections: dict[int, np.ndarray],
    K: np.ndarray,
    dist: np.ndarray | None = None,
    cube: CubeSpec = CubeSpec(),
) -> tuple[np.ndarray, float] | None:
    """Pose of the cube in one image from its detected markers.

    Uses every detected marker's corners at once (IPPE on the best single marker as the start, then
    iterative refinement over all corners). Returns ``(T_cam_cube [4, 4], rms reprojection error in
    pixels)`` or ``None`` when no marker was detected. ``T_cam_cube`` maps cube-frame points to
    OpenCV camera coordinates.
    """
    import cv2  # deferred: OpenCV is slow to load, and the CLI imports this module (for CubeSpec)

    if not detections:
        return None
    dist = np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    ids = sorted(detections)
    obj = np.concatenate([cube.marker_corners(i) for i in ids])  # [4M, 3]
    img = np.concatenate([detections[i] for i in ids])  # [4M, 2]
    best = None
    for i in ids:
        # IPPE for one square marker: object points in the marker's own plane
        h = cube.marker_size / 2
        square = np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]], dtype=np.float64)
        ok, rvecs, tvecs, errs = cv2.solvePnPGeneric(
            square, detections[i], K, dist, flags=cv2.SOLVEPNP_IPPE_SQUARE
        )
        if not ok:
            continue
        c, n, r, u = cube.face_frame(cube.face_of(i))
        # marker-plane frame -> cube frame: x = right, y = up, z = normal
        T_cube_marker = np.eye(4)
        T_cube_marker[:3, :3] = np.stack([r, u, n], axis=1)
        T_cube_marker[:3, 3] = c
        for rv, tv in zip(rvecs, tvecs):
            T_cam_marker = np.eye(4)
            T_cam_marker[:3, :3] = cv2.Rodrigues(rv)[0]
            T_cam_marker[:3, 3] = tv.ravel()
            T = T_cam_marker @ np.linalg.inv(T_cube_marker)
            rv2 = cv2.Rodrigues(T[:3, :3])[0]
            proj, _ = cv2.projectPoints(obj, rv2, T[:3, 3], K, dist)
            err = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))
            if best is None or err < best[1]:
                best = (T, err)
    if best is None:
        return None
    T0 = best[0]
    rvec = cv2.Rodrigues(T0[:3, :3])[0]
    tvec = T0[:3, 3].reshape(3, 1).copy()
    if len(ids) > 1:
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec, tvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    err = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = np.asarray(tvec).ravel()
    return T, err


def marker_image(marker_id: int, pixels: int, cube: CubeSpec = CubeSpec()) -> np.ndarray:
    """The printed marker (black border included) as a ``pixels`` x ``pixels`` uint8 image."""
    import cv2  # deferred: OpenCV is slow to load, and the CLI imports this module (for CubeSpec)

    return cv2.aruco.generateImageMarker(cube.aruco_dictionary(), int(marker_id), int(pixels), borderBits=1)


def cube_surface_points(
    size: float,
    n: int,
    rng: np.random.Generator,
    faces: tuple[str, ...] = FACE_NAMES,
    noise: float = 0.0,
) -> np.ndarray:
    """Uniform samples on the given faces of a cube in the cube frame (bottom face centred on the
    origin, +z up), with optional isotropic Gaussian noise of std ``noise``. ``[n, 3]``.

    Used by the tests and benchmarks as a known cube; it is not part of the measurement.
    """
    spec = CubeSpec(size=size, marker_size=size)
    per = np.full(len(faces), n // len(faces))
    per[: n - per.sum()] += 1
    out = []
    for face, m in zip(faces, per):
        c, _, r, u = spec.face_frame(face)
        ab = rng.uniform(-size / 2, size / 2, (m, 2))
        out.append(c + ab[:, :1] * r + ab[:, 1:] * u)
    pts = np.concatenate(out)
    if noise > 0:
        pts = pts + rng.normal(0, noise, pts.shape)
    return pts

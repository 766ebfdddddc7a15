"""Small triangle-mesh toolkit for the synthetic scene: grids, tubes, surfaces of revolution, boxes.

Every part of the scene is a :class:`Mesh` with per-vertex position, normal, texture coordinate and
colour, plus per-mesh texture layer, class id (organ or scene part) and instance id. Meshes are built
with numpy and handed to moderngl in one vertex buffer (see :mod:`plantsplat.synth.render`).

Example:
    >>> m = box_mesh((0, 0, 0), (2, 2, 2), cls=30)
    >>> m.v.shape, m.f.shape
    ((20, 3), (10, 3))
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from plantsplat.cube import FACE_NAMES

# class ids written by the id pass (0 = nothing drawn)
LEAF, PETIOLE, CROWN, FRUIT, PEDUNCLE, FLOWER = 1, 2, 3, 4, 5, 6
PLANT_CLASSES = (LEAF, PETIOLE, CROWN, FRUIT, PEDUNCLE, FLOWER)
CUBE_BASE = 10  # cube faces: 10 + face index (order of plantsplat.cube.FACE_NAMES)
CUBE_CLASSES = tuple(range(CUBE_BASE, CUBE_BASE + 6))
POT, SOIL, PLATFORM, FLOOR, WALL, FURNITURE, CALYX = 20, 21, 22, 30, 31, 32, 7
FOREGROUND_CLASSES = PLANT_CLASSES + (CALYX,) + CUBE_CLASSES
CLASS_NAMES = {0: "nothing", LEAF: "leaf", PETIOLE: "petiole", CROWN: "crown", FRUIT: "fruit", PEDUNCLE: "peduncle",
               FLOWER: "flower", CALYX: "calyx", **{CUBE_BASE + i: f"cube {face}" for i, face in enumerate(FACE_NAMES)},
               POT: "pot", SOIL: "soil", PLATFORM: "platform", FLOOR: "floor", WALL: "wall", FURNITURE: "furniture"}
"""Name of each class id (the id pass, and the capture's ``classes/`` maps)."""
ORGAN_OF_CLASS = {LEAF: 1, PETIOLE: 2, CROWN: 3, FRUIT: 4, CALYX: 4, PEDUNCLE: 5, FLOWER: 6}
"""Organ code written in the PLYs (1 leaf, 2 petiole, 3 crown, 4 fruit, 5 peduncle, 6 flower)."""


@dataclass
class Mesh:
    """Triangles with per-vertex attributes (cm, world frame)."""

    v: np.ndarray  # [N, 3] positions
    f: np.ndarray  # [M, 3] vertex indices
    uv: np.ndarray  # [N, 2] texture coordinates (layer space, may repeat)
    col: np.ndarray  # [N, 3] albedo multiplier in [0, 1]
    n: np.ndarray | None = None  # [N, 3] normals (computed from faces when None)
    layer: int = 0  # texture-array layer
    cls: int = 0  # class id (see constants above)
    instance: int = -1  # organ instance (leaf / fruit / flower index), -1 when none
    spec: float = 0.0  # specular strength (glossy fruit)
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        self.v = np.asarray(self.v, dtype=np.float64).reshape(-1, 3)
        self.f = np.asarray(self.f, dtype=np.int64).reshape(-1, 3)
        self.uv = np.asarray(self.uv, dtype=np.float64).reshape(-1, 2)
        col = np.asarray(self.col, dtype=np.float64)
        self.col = np.broadcast_to(col, (len(self.v), 3)).copy() if col.ndim == 1 else col.reshape(-1, 3)
        if self.n is None:
            self.n = vertex_normals(self.v, self.f)
        else:
            self.n = np.asarray(self.n, dtype=np.float64).reshape(-1, 3)

    def transformed(self, R: np.ndarray, t: np.ndarray) -> Mesh:
        """A copy moved by ``x -> R x + t``."""
        return Mesh(self.v @ R.T + t, self.f, self.uv, self.col, self.n @ R.T, self.layer, self.cls,
                    self.instance, self.spec, dict(self.extra))

    def area(self) -> np.ndarray:
        """Triangle areas ``[M]`` (cm^2)."""
        a, b, c = (self.v[self.f[:, i]] for i in range(3))
        return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


def vertex_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals ``[N, 3]`` (unit; +z for isolated vertices)."""
    n = np.zeros_like(v)
    if len(f):
        fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # [M, 3]
        for i in range(3):
            np.add.at(n, f[:, i], fn)
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    out = np.where(ln > 1e-12, n / np.maximum(ln, 1e-12), np.array([0.0, 0.0, 1.0]))
    return out


def grid_faces(nu: int, nv: int, wrap_v: bool = False) -> np.ndarray:
    """Two triangles per cell of an ``nu x nv`` vertex grid (row-major). ``[M, 3]``."""
    cols = nv if wrap_v else nv - 1
    i, j = np.meshgrid(np.arange(nu - 1), np.arange(cols), indexing="ij")
    i, j = i.ravel(), j.ravel()
    j1 = (j + 1) % nv
    a, b, c, d = i * nv + j, i * nv + j1, (i + 1) * nv + j, (i + 1) * nv + j1
    return np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])


def grid_mesh(P: np.ndarray, UV: np.ndarray, col, wrap_v: bool = False, **kw) -> Mesh:
    """Mesh of a parametric surface sampled on a grid: ``P [nu, nv, 3]``, ``UV [nu, nv, 2]``."""
    nu, nv = P.shape[:2]
    return Mesh(P.reshape(-1, 3), grid_faces(nu, nv, wrap_v), UV.reshape(-1, 2), col, **kw)


def frames_along(curve: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Parallel-transport frames along a polyline ``[K, 3]``: tangents, normals, binormals ``[K, 3]``."""
    t = np.gradient(curve, axis=0)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    ref = np.array([0.0, 0.0, 1.0]) if abs(t[0, 2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    n = np.empty_like(t)
    n0 = np.cross(t[0], ref)
    n[0] = n0 / np.linalg.norm(n0)
    for k in range(1, len(t)):
        m = n[k - 1] - t[k] * np.dot(n[k - 1], t[k])
        n[k] = m / max(np.linalg.norm(m), 1e-12)
    b = np.cross(t, n)
    return t, n, b


def tube_mesh(curve: np.ndarray, radius, sides: int = 6, col=(1, 1, 1), uv_scale: float = 1.0, **kw) -> Mesh:
    """A tube of ``sides`` facets around the polyline ``curve [K, 3]``; ``radius`` scalar or ``[K]``."""
    curve = np.asarray(curve, dtype=np.float64)
    r = np.broadcast_to(np.asarray(radius, dtype=np.float64), (len(curve),))
    _, n, b = frames_along(curve)
    ang = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    ring = np.cos(ang)[None, :, None] * n[:, None, :] + np.sin(ang)[None, :, None] * b[:, None, :]  # [K, S, 3]
    P = curve[:, None, :] + r[:, None, None] * ring
    seg = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(curve, axis=0), axis=1))])
    UV = np.stack(np.broadcast_arrays(seg[:, None] * uv_scale, ang[None, :] / (2 * np.pi)), -1)
    m = grid_mesh(P, UV, col, wrap_v=True, n=ring.reshape(-1, 3), **kw)
    return m


def revolution_mesh(profile_h: np.ndarray, profile_r: np.ndarray, origin, axis, sides: int = 16, col=(1, 1, 1),
                    uv_repeat: float = 1.0, **kw) -> Mesh:
    """Surface of revolution: radius ``profile_r [K]`` at distance ``profile_h [K]`` along ``axis`` from ``origin``."""
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    ref = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(axis, ref)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    ang = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    dirs = np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2  # [S, 3]
    P = np.asarray(origin, dtype=np.float64) + profile_h[:, None, None] * axis + profile_r[:, None, None] * dirs[None]
    hh = (profile_h - profile_h.min()) / max(np.ptp(profile_h), 1e-9)
    UV = np.stack(np.broadcast_arrays(ang[None, :] / (2 * np.pi) * uv_repeat, hh[:, None]), -1)
    return grid_mesh(P, UV, col, wrap_v=True, **kw)


def quad_mesh(corners: np.ndarray, uv: np.ndarray, col=(1, 1, 1), **kw) -> Mesh:
    """One planar quad from 4 corners (counter-clockwise seen from the front) and their uv ``[4, 2]``."""
    corners = np.asarray(corners, dtype=np.float64)
    nrm = np.cross(corners[1] - corners[0], corners[3] - corners[0])
    nrm = nrm / np.linalg.norm(nrm)
    return Mesh(corners, [[0, 1, 2], [0, 2, 3]], uv, col, n=np.tile(nrm, (4, 1)), **kw)


def box_mesh(lo, hi, col=(1, 1, 1), uv_per_cm: float = 1 / 50, skip_bottom: bool = True, **kw) -> Mesh:
    """Axis-aligned box from ``lo`` to ``hi`` (cm); texture repeats every ``1/uv_per_cm`` cm."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    faces = [
        ([x1, y0, z0], [x1, y1, z0], [x1, y1, z1], [x1, y0, z1]),
        ([x0, y1, z0], [x0, y0, z0], [x0, y0, z1], [x0, y1, z1]),
        ([x1, y1, z0], [x0, y1, z0], [x0, y1, z1], [x1, y1, z1]),
        ([x0, y0, z0], [x1, y0, z0], [x1, y0, z1], [x0, y0, z1]),
        ([x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]),
    ]
    if not skip_bottom:
        faces.append(([x0, y1, z0], [x1, y1, z0], [x1, y0, z0], [x0, y0, z0]))
    meshes = []
    for c in faces:
        c = np.array(c)
        w = np.linalg.norm(c[1] - c[0]) * uv_per_cm
        h = np.linalg.norm(c[3] - c[0]) * uv_per_cm
        meshes.append(quad_mesh(c, np.array([[0, 0], [w, 0], [w, h], [0, h]]), col, **kw))
    return merge(meshes)


def cylinder_mesh(centre, radius: float, z0: float, z1: float, sides: int = 48, col=(1, 1, 1), cap: bool = True,
                  uv_per_cm: float = 1 / 50, **kw) -> Mesh:
    """Vertical cylinder (side and optional top cap) with its axis through ``centre`` (x, y)."""
    cx, cy = centre[0], centre[1]
    ang = np.linspace(0, 2 * np.pi, sides + 1)
    zs = np.array([z0, z1])
    P = np.stack(np.broadcast_arrays(cx + radius * np.cos(ang)[None, :], cy + radius * np.sin(ang)[None, :],
                                     zs[:, None]), -1)
    UV = np.stack(np.broadcast_arrays(ang[None, :] * radius * uv_per_cm, zs[:, None] * uv_per_cm), -1)
    N = np.stack(np.broadcast_arrays(np.cos(ang)[None, :], np.sin(ang)[None, :], 0 * zs[:, None]), -1)
    side = grid_mesh(P, UV, col, n=N.reshape(-1, 3), **kw)
    if not cap:
        return side
    return merge([side, disk_mesh((cx, cy, z1), radius, sides, col, uv_per_cm=uv_per_cm, **kw)])


def disk_mesh(centre, radius: float, sides: int = 48, col=(1, 1, 1), uv_per_cm: float = 1 / 50, rings: int = 1,
              **kw) -> Mesh:
    """Horizontal disk facing +z, triangulated in ``rings`` concentric rings."""
    c = np.asarray(centre, float)
    ang = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    rr = np.linspace(0, radius, rings + 1)[1:]
    pts = [c]
    for r in rr:
        pts.extend(c + np.stack([r * np.cos(ang), r * np.sin(ang), 0 * ang], 1))
    v = np.array(pts).reshape(-1, 3)
    f = [[0, 1 + j, 1 + (j + 1) % sides] for j in range(sides)]
    for k in range(rings - 1):
        a0, b0 = 1 + k * sides, 1 + (k + 1) * sides
        for j in range(sides):
            j1 = (j + 1) % sides
            f += [[a0 + j, b0 + j, b0 + j1], [a0 + j, b0 + j1, a0 + j1]]
    uv = (v[:, :2] - c[:2]) * uv_per_cm
    return Mesh(v, f, uv, col, n=np.tile([0.0, 0.0, 1.0], (len(v), 1)), **kw)


def merge(meshes: list[Mesh]) -> Mesh:
    """Concatenate meshes that share layer/class/instance (attributes of the first are kept)."""
    meshes = [m for m in meshes if len(m.f)]
    offs = np.cumsum([0] + [len(m.v) for m in meshes[:-1]])
    m0 = meshes[0]
    return Mesh(np.concatenate([m.v for m in meshes]), np.concatenate([m.f + o for m, o in zip(meshes, offs)]),
                np.concatenate([m.uv for m in meshes]), np.concatenate([m.col for m in meshes]),
                np.concatenate([m.n for m in meshes]), m0.layer, m0.cls, m0.instance, m0.spec, dict(m0.extra))


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def rot_axis(axis, a: float) -> np.ndarray:
    """Rotation matrix about a unit ``axis`` by angle ``a`` (Rodrigues)."""
    k = np.asarray(axis, float)
    k = k / np.linalg.norm(k)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K

"""The synthetic scene around the plant: pot and soil, round platform, marker cube, cluttered room, lights.

World frame: origin on the platform top (the ground plane the pot and cube stand on) under the pot
centre, +z up, centimetres. The floor of the room is ``platform_height`` below.

Example:
    >>> import numpy as np
    >>> sc = make_scene(np.random.default_rng(0))
    >>> sorted(sc.keys())[:4]
    ['cube', 'lights', 'meshes', 'plant_info']
"""

from __future__ import annotations

import numpy as np

from plantsplat.cube import FACE_NAMES, CubeSpec
from plantsplat.synth import textures as T
from plantsplat.synth.camera import max_distance
from plantsplat.synth.mesh import (
    CUBE_BASE,
    FLOOR,
    FURNITURE,
    PLATFORM,
    POT,
    SOIL,
    WALL,
    Mesh,
    box_mesh,
    cylinder_mesh,
    disk_mesh,
    grid_mesh,
    quad_mesh,
    revolution_mesh,
    rot_z,
)
from plantsplat.synth.plant import Pot, make_plant, make_pot

Z = np.array([0.0, 0.0, 1.0])


def pot_meshes(pot: Pot) -> list[Mesh]:
    """Outer wall, rim lip and top, inner wall and the soil disk."""
    col = np.array(pot.colour)
    out = []
    zs = np.linspace(0, pot.rim_z - 1.2, 6)
    out.append(revolution_mesh(zs, pot.bottom_radius + (pot.top_radius - pot.bottom_radius) * zs / pot.height,
                               (0, 0, 0), Z, 48, col, uv_repeat=6, layer=T.POT, cls=POT))
    # lip: a short band of radius top+lip, and the flat top ring
    out.append(cylinder_mesh((0, 0), pot.top_radius + pot.lip, pot.rim_z - 1.2, pot.rim_z, 48, col, cap=False,
                             layer=T.POT, cls=POT))
    ang = np.linspace(0, 2 * np.pi, 49)
    r_in = pot.top_radius - pot.wall
    rr = np.array([r_in, pot.top_radius + pot.lip])
    P = np.stack(np.broadcast_arrays(rr[:, None] * np.cos(ang), rr[:, None] * np.sin(ang), pot.rim_z + 0 * ang), -1)
    UV = np.stack(np.broadcast_arrays(ang[None] / np.pi, rr[:, None] / 10), -1)
    out.append(grid_mesh(P, UV, col, n=np.tile(Z, (98, 1)), layer=T.POT, cls=POT))
    zi = np.linspace(pot.soil_z - 0.01, pot.rim_z, 3)
    out.append(revolution_mesh(zi, pot.radius_at(0) * 0 + np.interp(zi, [0, pot.height],
                                                                       [pot.bottom_radius - pot.wall, r_in]),
                               (0, 0, 0), Z, 48, col * 0.7, uv_repeat=6, layer=T.POT, cls=POT))
    r_soil = np.interp(pot.soil_z, [0, pot.height], [pot.bottom_radius - pot.wall, r_in])
    out.append(disk_mesh((0, 0, pot.soil_z), r_soil, 48, (1, 1, 1), uv_per_cm=1 / 12, rings=4, layer=T.SOIL, cls=SOIL))
    return out


def cube_meshes(cube: CubeSpec, T_world_cube: np.ndarray) -> list[Mesh]:
    """The six faces of the marker cube, each textured with its marker layer (face texels [6, 506))."""
    out = []
    h = cube.size / 2
    lo, hi = 6 / T.SIZE, (6 + T.MARKER_FACE_TEXELS) / T.SIZE
    for i, face in enumerate(FACE_NAMES):
        c, n, r, u = cube.face_frame(face)
        # TL, TR, BR, BL seen from outside; image rows grow downward = texture v grows
        corners = np.stack([c - r * h + u * h, c + r * h + u * h, c + r * h - u * h, c - r * h - u * h])
        uv = np.array([[lo, lo], [hi, lo], [hi, hi], [lo, hi]])
        quad = quad_mesh(corners, uv, (1, 1, 1), layer=T.MARKER0 + i, cls=CUBE_BASE + i, instance=i)
        quad.n[:] = n
        out.append(quad.transformed(T_world_cube[:3, :3], T_world_cube[:3, 3]))
    return out


class _Placer:
    """Free spots on the floor, away from the platform and from what is already placed."""

    def __init__(self, rng, room, avoid_r):
        self.rng, self.room, self.avoid_r = rng, room, avoid_r
        self.placed: list[tuple[np.ndarray, float]] = []

    def free_spot(self, radius):
        (x0, x1), (y0, y1) = self.room
        for _ in range(60):
            p = np.array([self.rng.uniform(x0 + radius, x1 - radius), self.rng.uniform(y0 + radius, y1 - radius)])
            if np.linalg.norm(p) < self.avoid_r + radius:
                continue
            if all(np.linalg.norm(p - q) > radius + s for q, s in self.placed):
                self.placed.append((p, radius))
                return p
        return None


_BOX_LAYERS = [T.CARDBOARD, T.CARDBOARD, T.PRINT, T.FABRIC, T.CHECKER, T.WOOD, T.GREEN_DECOY, T.FOLIAGE_PRINT]


def _box_item(rng, kind: str, placer: _Placer, floor_z: float):
    """A box, a stack of two boxes or a green decoy box."""
    sx, sy, sz = rng.uniform(20, 60), rng.uniform(20, 60), rng.uniform(15, 70)
    p = placer.free_spot(0.5 * np.hypot(sx, sy))
    if p is None:
        return None
    layer = T.GREEN_DECOY if kind == "green" else int(rng.choice(_BOX_LAYERS))
    col = rng.uniform(0.75, 1.0, 3)
    R = rot_z(rng.uniform(0, np.pi))
    b = box_mesh((-sx / 2, -sy / 2, 0), (sx / 2, sy / 2, sz), col, uv_per_cm=1 / max(sx, sy, sz),
                 layer=layer, cls=FURNITURE)
    meshes = [b.transformed(R, np.array([p[0], p[1], floor_z]))]
    if kind == "stack":
        s2 = rng.uniform(0.5, 0.9)
        b2 = box_mesh((-sx * s2 / 2, -sy * s2 / 2, sz), (sx * s2 / 2, sy * s2 / 2, sz + rng.uniform(10, 40)),
                      rng.uniform(0.75, 1.0, 3), uv_per_cm=1 / 40, layer=int(rng.choice(_BOX_LAYERS)),
                      cls=FURNITURE)
        meshes.append(b2.transformed(R @ rot_z(rng.uniform(-0.4, 0.4)), np.array([p[0], p[1], floor_z])))
    return meshes, dict(kind=kind, xy=p.tolist(), layer=int(layer))


def _table_item(rng, placer: _Placer, floor_z: float):
    """A table with a few things on it."""
    sx, sy, hz = rng.uniform(60, 120), rng.uniform(50, 80), rng.uniform(70, 80)
    p = placer.free_spot(0.5 * np.hypot(sx, sy))
    if p is None:
        return None
    R = rot_z(rng.uniform(0, np.pi))
    parts = [box_mesh((-sx / 2, -sy / 2, hz - 3), (sx / 2, sy / 2, hz), (1, 1, 1), uv_per_cm=1 / 80,
                      layer=T.WOOD, cls=FURNITURE)]
    for dx in (-1, 1):
        for dy in (-1, 1):
            cx, cy = dx * (sx / 2 - 4), dy * (sy / 2 - 4)
            parts.append(box_mesh((cx - 2, cy - 2, 0), (cx + 2, cy + 2, hz - 3), (0.8, 0.8, 0.8),
                                  uv_per_cm=1 / 80, layer=T.WOOD, cls=FURNITURE))
    for _ in range(int(rng.integers(1, 4))):
        bx, by, bz = rng.uniform(8, 25), rng.uniform(8, 25), rng.uniform(5, 30)
        cx, cy = rng.uniform(-sx / 2 + bx, sx / 2 - bx), rng.uniform(-sy / 2 + by, sy / 2 - by)
        parts.append(box_mesh((cx - bx / 2, cy - by / 2, hz), (cx + bx / 2, cy + by / 2, hz + bz),
                              rng.uniform(0.7, 1, 3), uv_per_cm=1 / 30,
                              layer=int(rng.choice([T.PRINT, T.CARDBOARD, T.GREEN_DECOY, T.FABRIC])),
                              cls=FURNITURE))
    return [part.transformed(R, np.array([p[0], p[1], floor_z])) for part in parts], dict(kind="table", xy=p.tolist())


def _bucket_item(rng, placer: _Placer, floor_z: float):
    """A bucket, green in 40 % of the draws."""
    r, hz = rng.uniform(10, 25), rng.uniform(20, 50)
    p = placer.free_spot(r)
    if p is None:
        return None
    green = rng.random() < 0.4
    col = np.array([0.15, 0.55, 0.2]) if green else rng.uniform(0.1, 0.9, 3)
    mesh = cylinder_mesh((p[0], p[1]), r, floor_z, floor_z + hz, 32, col, uv_per_cm=1 / 40,
                         layer=T.PLATFORM, cls=FURNITURE)
    return [mesh], dict(kind="green bucket" if green else "bucket", xy=p.tolist())


def _shelf_books(rng, w: float, d: float, hz: float) -> list[Mesh]:
    parts = []
    for z in np.linspace(0, hz - 2, 4)[:-1]:
        xx = -w / 2 + 2
        while xx < w / 2 - 6:
            bw = rng.uniform(2, 10)
            bh = rng.uniform(10, min(30, (hz - 2) / 3 - 4))
            parts.append(box_mesh((xx, -d / 2 + 2, z + 2), (xx + bw, d / 2 - 4, z + 2 + bh),
                                  np.array(rng.uniform(0.2, 1.0, 3)), uv_per_cm=1 / 20,
                                  layer=int(rng.choice([T.PRINT, T.FABRIC, T.WHITE, T.CHECKER])),
                                  cls=FURNITURE))
            xx += bw + rng.uniform(0, 4)
    return parts


def _shelf_item(rng, placer: _Placer, floor_z: float):
    """A shelf against a wall with books and boxes."""
    (x0, x1), (y0, y1) = placer.room
    wall = int(rng.integers(4))
    w, d, hz = rng.uniform(60, 120), rng.uniform(25, 40), rng.uniform(100, 200)
    if wall < 2:
        x = x0 + d / 2 + 1 if wall == 0 else x1 - d / 2 - 1
        y = rng.uniform(y0 + w / 2, y1 - w / 2)
        R = rot_z(np.pi / 2)
    else:
        y = y0 + d / 2 + 1 if wall == 2 else y1 - d / 2 - 1
        x = rng.uniform(x0 + w / 2, x1 - w / 2)
        R = np.eye(3)
    p = np.array([x, y])
    if np.linalg.norm(p) < placer.avoid_r + 0.5 * np.hypot(w, d):
        return None
    placer.placed.append((p, 0.5 * np.hypot(w, d)))
    parts = [box_mesh((-w / 2, -d / 2, z), (w / 2, d / 2, z + 2), (0.9, 0.9, 0.9), uv_per_cm=1 / 60,
                      layer=T.WOOD, cls=FURNITURE) for z in np.linspace(0, hz - 2, 4)]
    for side in (-1, 1):
        parts.append(box_mesh((side * w / 2 - 1, -d / 2, 0), (side * w / 2 + 1, d / 2, hz), (0.9, 0.9, 0.9),
                              uv_per_cm=1 / 60, layer=T.WOOD, cls=FURNITURE))
    parts += _shelf_books(rng, w, d, hz)
    return [part.transformed(R, np.array([p[0], p[1], floor_z])) for part in parts], dict(kind="shelf", xy=p.tolist())


def _furniture(rng, room, floor_z, avoid_r) -> tuple[list[Mesh], list[dict]]:
    """Boxes, a table, shelves, buckets and green decoys placed on the floor around the platform."""
    placer = _Placer(rng, room, avoid_r)
    meshes, items = [], []
    n_items = int(rng.integers(10, 22))
    for _ in range(n_items):
        kind = rng.choice(["box", "box", "stack", "table", "bucket", "green", "shelf"])
        if kind in ("box", "green", "stack"):
            made = _box_item(rng, str(kind), placer, floor_z)
        elif kind == "table":
            made = _table_item(rng, placer, floor_z)
        elif kind == "bucket":
            made = _bucket_item(rng, placer, floor_z)
        else:
            made = _shelf_item(rng, placer, floor_z)
        if made is not None:
            meshes.extend(made[0])
            items.append(made[1])
    return meshes, items


def make_scene(rng: np.random.Generator, cube: CubeSpec = CubeSpec(), hard: bool = False) -> dict:
    """Draw the whole scene for one seed.

    Returns a dict with ``meshes`` (list of :class:`Mesh`), ``plant_meshes`` (the plant's own meshes),
    ``cube`` (spec, ``T_world_cube``, marker corners), ``pot``, ``platform``, ``room``, ``lights`` and
    ``plant_info``. ``hard``: the cube 5-15 cm from the pot's rim and blank walls (the same draws, mapped
    onto those ranges, so that a seed's plant is the same either way).
    """
    pot = make_pot(rng)
    # cube beside the pot on the platform
    cube_az = rng.uniform(0, 2 * np.pi)
    corner = cube.size / 2 * np.sqrt(2) * rng.uniform(0.75, 1.0)
    gap = rng.uniform(0.5, 6)
    if hard:
        gap = 5.0 + (gap - 0.5) / 5.5 * 10.0
    cube_d = pot.top_radius + pot.lip + corner + gap
    yaw = rng.uniform(0, np.pi / 2)
    T_wc = np.eye(4)
    T_wc[:3, :3] = rot_z(yaw)
    T_wc[:3, 3] = [cube_d * np.cos(cube_az), cube_d * np.sin(cube_az), 0.0]

    def hits_cube(pts: np.ndarray, margin: float = 0.5) -> bool:
        pc = (pts - T_wc[:3, 3]) @ T_wc[:3, :3]  # cube frame
        h = cube.size / 2 + margin
        return bool(np.any((np.abs(pc[:, 0]) < h) & (np.abs(pc[:, 1]) < h) & (pc[:, 2] < cube.size + margin)))

    plant_meshes, plant_info = make_plant(rng, pot, avoid_azimuth=cube_az, obstacle=hits_cube)
    # platform (a round bin) big enough for pot and cube
    plat_r = max(cube_d + cube.size * 0.75, pot.top_radius + 10) + rng.uniform(4, 15)
    plat_h = rng.uniform(35, 80)
    plat_col = [np.array(c) for c in ([0.2, 0.22, 0.25], [0.75, 0.75, 0.72], [0.1, 0.2, 0.45], [0.45, 0.3, 0.2],
                                      [0.35, 0.35, 0.35])][int(rng.integers(5))]
    floor_z = -plat_h
    meshes: list[Mesh] = []
    meshes.append(cylinder_mesh((0, 0), plat_r, floor_z, 0.0, 64, plat_col, uv_per_cm=1 / 40, layer=T.PLATFORM,
                                cls=PLATFORM))
    meshes += pot_meshes(pot)
    meshes += cube_meshes(cube, T_wc)
    # room: the camera circles at most `clearance` cm from the pot axis; furniture and walls stay beyond
    pv = np.concatenate([m.v for m in plant_meshes])
    reach = max(np.linalg.norm(pv[:, :2], axis=1).max(), cube_d + cube.size * 0.75)
    clearance = max(max_distance(reach), plat_r) + 15.0
    x0, x1 = -(clearance + rng.uniform(40, 180)), clearance + rng.uniform(40, 180)
    y0, y1 = -(clearance + rng.uniform(40, 180)), clearance + rng.uniform(40, 180)
    wall_h = rng.uniform(240, 300)
    tile = rng.uniform(40, 90)
    meshes.append(quad_mesh(np.array([[x0, y0, floor_z], [x1, y0, floor_z], [x1, y1, floor_z], [x0, y1, floor_z]]),
                            np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]) / tile, (1, 1, 1),
                            layer=T.FLOOR, cls=FLOOR))
    top = floor_z + wall_h
    meshes.append(quad_mesh(np.array([[x0, y1, top], [x1, y1, top], [x1, y0, top], [x0, y0, top]]),
                            np.zeros((4, 2)), (0.9, 0.9, 0.9), layer=T.WHITE, cls=WALL))
    wall_corners = [((x0, y0), (x0, y1)), ((x0, y1), (x1, y1)), ((x1, y1), (x1, y0)), ((x1, y0), (x0, y0))]
    plain = rng.random() < 0.25 or hard
    for k, (a, b) in enumerate(wall_corners):
        a, b = np.array(a), np.array(b)
        length = np.linalg.norm(b - a)
        c = np.array([[*a, floor_z], [*b, floor_z], [*b, top], [*a, top]])
        meshes.append(quad_mesh(c, np.array([[0, 0], [length, 0], [length, wall_h], [0, wall_h]]) / 150,
                                (1, 1, 1), layer=T.WALL_A if k % 2 == 0 else T.WALL_B, cls=WALL))
        if plain:
            continue
        dirv = (b - a) / length
        inward = np.array([-dirv[1], dirv[0]])  # walls are listed clockwise seen from above: left is inside
        for _ in range(int(rng.integers(0, 4))):
            w, h = rng.uniform(30, 100), rng.uniform(30, 90)
            s = rng.uniform(w / 2 + 5, length - w / 2 - 5)
            zc = floor_z + rng.uniform(90, wall_h - h / 2 - 20)
            p = a + dirv * s + inward * 0.5
            q = np.array([[*(p - dirv * w / 2), zc - h / 2], [*(p + dirv * w / 2), zc - h / 2],
                          [*(p + dirv * w / 2), zc + h / 2], [*(p - dirv * w / 2), zc + h / 2]])
            layer = int(rng.choice([T.POSTER, T.POSTER, T.FOLIAGE_PRINT, T.CHECKER, T.PRINT]))
            meshes.append(quad_mesh(q, np.array([[0, 1], [1, 1], [1, 0], [0, 0]]), (1, 1, 1), layer=layer, cls=WALL))
    furn, items = _furniture(rng, ((x0, x1), (y0, y1)), floor_z, clearance)
    meshes += furn
    # lights: a ceiling key light (direction towards the light), a fill and hemisphere ambient
    key_az, key_el = rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(45, 80))
    key_dir = np.array([np.cos(key_az) * np.cos(key_el), np.sin(key_az) * np.cos(key_el), np.sin(key_el)])
    warm = rng.uniform(0, 1)
    key_col = np.array([1.0, 0.95 - 0.08 * warm, 0.88 - 0.2 * warm]) * rng.uniform(1.6, 2.4)
    fill_az = key_az + np.pi + rng.uniform(-0.8, 0.8)
    fill_dir = np.array([np.cos(fill_az) * 0.8, np.sin(fill_az) * 0.8, 0.6])
    lights = dict(key_dir=key_dir, key_colour=key_col, fill_dir=fill_dir / np.linalg.norm(fill_dir),
                  fill_colour=np.full(3, rng.uniform(0.25, 0.5)), sky_colour=np.full(3, rng.uniform(0.35, 0.55)),
                  ground_colour=np.full(3, rng.uniform(0.12, 0.25)))
    markers = {str(mid): (cube.marker_corners(mid) @ T_wc[:3, :3].T + T_wc[:3, 3]) for mid in cube.face_ids}
    return dict(
        meshes=plant_meshes + meshes,
        plant_meshes=plant_meshes,
        cube=dict(spec=cube, T_world_cube=T_wc, markers=markers, azimuth_deg=float(np.degrees(cube_az) % 360),
                  distance_cm=float(cube_d)),
        pot=pot,
        platform=dict(radius_cm=float(plat_r), height_cm=float(plat_h), colour=plat_col.tolist()),
        room=dict(x_cm=[float(x0), float(x1)], y_cm=[float(y0), float(y1)], floor_z_cm=float(floor_z),
                  camera_clearance_cm=float(clearance),
                  wall_height_cm=float(wall_h), plain_walls=bool(plain), n_items=len(items), items=items),
        lights={k: np.asarray(v).tolist() for k, v in lights.items()},
        plant_info=plant_info,
    )

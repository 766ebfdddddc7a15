"""A procedural strawberry plant (Fragaria x ananassa, fruiting stage) in a pot.

The plant is built from the crown up, in the world frame of ``plantsplat synth`` (cm, +z up, pot axis
through x = y = 0, platform top at z = 0):

- crown: a small dome on the soil;
- 5-15 trifoliate leaves: petioles that rise from the crown and arch outward (quadratic Bezier tubes),
  each ending in three ovate leaflets with serrated margins (forward-pointing teeth), cupped upward,
  folded along the midrib and drooping toward the tip; leaf size and reach depend on the azimuth
  (two random harmonics) so that the crown is asymmetric (width1 != width2);
- 1-10 conical red (some unripe) fruits with achenes (texture) and a green calyx, each on a thin
  peduncle; about half hang over the pot rim;
- 0-3 white five-petalled flowers with a yellow centre.

No organ pierces the pot, soil or platform: leaves stay above the rim, hanging fruits clear the rim
lip. Plants whose traits fall outside the target ranges (height 12-35 cm, width1 18-50 cm) are
re-drawn from the same random stream, so the result is still a pure function of the seed.

Example:
    >>> import numpy as np
    >>> pot = make_pot(np.random.default_rng(0))
    >>> meshes, info = make_plant(np.random.default_rng(0), pot)
    >>> 5 <= info["n_leaves"] <= 15 and info["n_fruits"] >= 1
    True
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from plantsplat.synth import textures as T
from plantsplat.synth.mesh import (
    CALYX,
    CROWN,
    FLOWER,
    FRUIT,
    LEAF,
    PEDUNCLE,
    PETIOLE,
    Mesh,
    grid_mesh,
    merge,
    revolution_mesh,
    rot_axis,
    tube_mesh,
)
from plantsplat.traitdefs import pca_widths, plant_height

Z = np.array([0.0, 0.0, 1.0])
HEIGHT_RANGE = (12.0, 35.0)
WIDTH1_RANGE = (18.0, 50.0)


@dataclass
class Pot:
    """A tapered round pot standing on the platform (z = 0), axis through the origin."""

    top_radius: float
    bottom_radius: float
    height: float
    soil_depth: float  # rim height above the soil surface
    wall: float = 0.5
    lip: float = 0.6  # outward rim lip
    colour: tuple = (0.6, 0.3, 0.2)
    kind: str = "terracotta"

    @property
    def soil_z(self) -> float:
        return self.height - self.soil_depth

    @property
    def rim_z(self) -> float:
        return self.height

    def radius_at(self, z: float) -> float:
        return self.bottom_radius + (self.top_radius - self.bottom_radius) * np.clip(z / self.height, 0, 1)

    def as_dict(self) -> dict:
        d = asdict(self)
        d.update(soil_z_cm=self.soil_z, rim_z_cm=self.rim_z)
        return {k if k.endswith("_cm") or k in ("colour", "kind") else k + "_cm": v for k, v in d.items()}


def make_pot(rng: np.random.Generator) -> Pot:
    """Draw a pot: terracotta, black, grey or (rarely) green plastic, 14-22 cm across."""
    kinds = [("terracotta", (0.62, 0.3, 0.18)), ("black plastic", (0.05, 0.05, 0.055)),
             ("grey plastic", (0.45, 0.45, 0.47)), ("white plastic", (0.85, 0.85, 0.82)),
             ("green plastic", (0.12, 0.35, 0.15))]
    k = int(rng.choice(len(kinds), p=[0.35, 0.3, 0.15, 0.12, 0.08]))
    top = float(rng.uniform(7.0, 11.0))
    return Pot(top_radius=top, bottom_radius=top * float(rng.uniform(0.7, 0.85)), height=float(rng.uniform(11, 17)),
               soil_depth=float(rng.uniform(1.0, 2.5)), colour=kinds[k][1], kind=kinds[k][0])


def _bezier(P: np.ndarray, n: int) -> np.ndarray:
    """Bezier curve of any degree through control points ``P [D+1, 3]`` sampled at ``n`` points."""
    t = np.linspace(0, 1, n)[:, None]
    pts = P.copy()
    out = np.empty((n, 3))
    # de Casteljau
    for i in range(n):
        q = pts.copy()
        while len(q) > 1:
            q = (1 - t[i]) * q[:-1] + t[i] * q[1:]
        out[i] = q[0]
    return out


def _unit(v):
    return v / np.linalg.norm(v)


def _leaflet(rng, origin, d, side, nrm, length, half_width, cup, fold, droop, n_teeth, depth, col, leaf_idx,
             senescence: float = 0.0):
    """One serrated, cupped leaflet as a grid mesh (midrib along ``d``, blade normal ``nrm``)."""
    smax = rng.uniform(0.5, 0.62)
    a = np.log(0.5) / np.log(smax)
    s = np.concatenate([np.linspace(0, 1, 16), (np.arange(n_teeth) + 0.02) / n_teeth,
                        (np.arange(n_teeth) + 0.5) / n_teeth, (np.arange(n_teeth) + 0.96) / n_teeth])
    s = np.unique(np.clip(s, 0, 1))
    shape = np.sin(np.pi * s**a).clip(0) ** 0.75
    frac = (n_teeth * s) % 1.0
    serr = np.where(s > 0.22, 1 - depth * (1 - frac), 1.0)
    w = half_width * shape * serr  # [nu]
    t = np.linspace(-1, 1, 7)
    S, Tt = np.meshgrid(s, t, indexing="ij")  # [nu, nv]
    W = w[:, None] * np.ones_like(Tt)
    x = S * length
    y = Tt * W
    z = cup * half_width * Tt**2 * shape[:, None] + fold * np.abs(Tt) * W - droop * length * S**2
    P = origin + x[..., None] * d + y[..., None] * side + z[..., None] * nrm
    UV = np.stack([S, (Tt + 1) / 2], -1)
    shade = 1.0 + 0.06 * rng.standard_normal()
    colv = np.broadcast_to(col * shade, S.shape + (3,)).copy()  # [nu, nv, 3]
    if senescence > 0:  # older leaves: yellow-brown from the margin and tip inward
        edge = np.clip((np.abs(Tt) * 0.6 + S * 0.6 - 0.55) / 0.45, 0, 1)[..., None] * senescence
        colv = colv * (1 - edge) + np.array([0.55, 0.45, 0.12]) * edge
    return grid_mesh(P, UV, colv.reshape(-1, 3), layer=T.LEAF_TOP, cls=LEAF, instance=leaf_idx)


def _leaf(rng, idx, crown, crown_r, azim, L, elev, leaflet_len, pot: Pot, tint, senescence: float = 0.0):
    """A trifoliate leaf: petiole tube + three leaflets. Returns meshes, the blade vertices and info."""
    h = np.array([np.cos(azim), np.sin(azim), 0.0])
    base = crown + h * crown_r * 0.5 + Z * 0.3
    Lh, Lv = L * np.cos(elev), L * np.sin(elev)
    tip = base + h * Lh + Z * Lv
    ctrl = base + h * Lh * rng.uniform(0.05, 0.4) + Z * Lv * rng.uniform(1.1, 1.4)
    curve = _bezier(np.stack([base, ctrl, tip]), 14)
    rad = np.linspace(0.22, 0.13, 14) * (leaflet_len / 5.0) ** 0.5
    pet_col = np.array([0.32, 0.45, 0.16]) * tint
    red_base = np.linspace(1, 0, 14)[:, None] ** 3 * np.array([0.25, -0.15, -0.05])
    pet_cols = np.repeat(np.clip(pet_col + red_base, 0, 1), 6, axis=0)
    petiole = tube_mesh(curve, rad, 6, pet_cols, uv_scale=0.05, layer=T.WHITE, cls=PETIOLE, instance=idx)
    # blade frame at the tip
    pitch = np.radians(rng.uniform(-15, 25))
    f = np.cos(pitch) * h + np.sin(pitch) * Z
    s = _unit(np.cross(Z, h))
    n = np.cross(f, s)
    roll = np.radians(rng.uniform(-20, 20))
    R = rot_axis(f, roll)
    s, n = R @ s, R @ n
    spread = np.radians(rng.uniform(50, 72))
    cup = rng.uniform(0.05, 0.35)
    fold = rng.uniform(0.0, 0.35)
    droop = rng.uniform(-0.02, 0.18)
    n_teeth = int(rng.integers(9, 15))
    depth = rng.uniform(0.05, 0.11)
    leaf_col = np.array([0.16, 0.36, 0.09]) * tint
    blades, stalks = [], []
    for k, th in enumerate((0.0, spread, -spread)):
        R = rot_axis(n, th)
        d, sd = R @ f, R @ s
        ln = leaflet_len * (1.0 if k == 0 else rng.uniform(0.82, 0.95))
        hw = ln * rng.uniform(0.34, 0.42)
        stalk = rng.uniform(0.5, 1.0) if k == 0 else 0.3  # petiolules: the terminal one is longer
        start = tip + d * stalk
        blades.append(_leaflet(rng, start, d, sd, n, ln, hw, cup, fold, droop, n_teeth, depth, leaf_col,
                               idx, senescence))
        stalks.append(tube_mesh(np.linspace(tip, start + d * 0.1, 3), 0.07, 5, pet_col, uv_scale=0.05,
                                layer=T.WHITE, cls=PETIOLE, instance=idx))
    blade = merge(blades)
    return [petiole, merge(stalks), blade], curve, blade.v, dict(azimuth_deg=float(np.degrees(azim) % 360),
                                                                 petiole_length_cm=float(L),
                                                  elevation_deg=float(np.degrees(elev)),
                                                  leaflet_length_cm=float(leaflet_len))


def _fruit_profile(n=20, shoulder: float = 0.07, taper: float = 0.75):
    """Radius profile along the fruit axis (0 = calyx, 1 = tip), max 1: conical for taper ~0.8, rounder below."""
    u = np.linspace(0, 1, n)
    g = (u / (u + shoulder)) ** 0.6 * (1 - u) ** taper
    return u, g / g.max()


def _fruit(rng, idx, attach, axis, length, radius, ripe: bool):
    """A conical strawberry hanging from ``attach`` along ``axis`` with a calyx of sepals."""
    u, g = _fruit_profile(shoulder=rng.uniform(0.04, 0.12), taper=rng.uniform(0.5, 0.95))
    col = np.array([0.72, 0.04, 0.05]) * rng.uniform(0.85, 1.1) if ripe else \
        np.array([0.85, 0.88, 0.6]) * rng.uniform(0.85, 1.0)
    body = revolution_mesh(u * length, g * radius, attach, axis, sides=16, col=np.clip(col, 0, 1),
                           uv_repeat=3.0, layer=T.FRUIT, cls=FRUIT, instance=idx, spec=0.5)
    # calyx: sepals radiating from the top, lifted slightly
    axis = _unit(axis)
    ref = np.array([1.0, 0, 0]) if abs(axis[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = _unit(np.cross(axis, ref))
    e2 = np.cross(axis, e1)
    sep = []
    ns = int(rng.integers(8, 12))
    for k in range(ns):
        a = 2 * np.pi * (k + rng.uniform(-0.2, 0.2)) / ns
        r = np.cos(a) * e1 + np.sin(a) * e2
        tt = r.copy()
        tt = np.cross(axis, r)
        ln = radius * rng.uniform(0.9, 1.3)
        sv = np.linspace(0, 1, 5)
        lift = rng.uniform(-0.1, 0.35)
        ctr = attach + axis * (0.15 * radius) + r[None] * (sv[:, None] * ln) - axis * (lift * ln * sv[:, None] ** 2)
        half = (np.sin(np.pi * np.clip(sv * 0.9 + 0.1, 0, 1)) * 0.22 * ln)[:, None]
        P = np.stack([ctr - tt * half, ctr + tt * half], 1)
        UV = np.stack(np.broadcast_arrays(sv[:, None], np.array([0.3, 0.7])[None]), -1)
        sep.append(grid_mesh(P, UV, (0.2, 0.42, 0.12), layer=T.LEAF_TOP, cls=CALYX, instance=idx))
    return [body, merge(sep)]


def _flower(rng, idx, centre, normal, radius):
    normal = _unit(normal)
    ref = np.array([1.0, 0, 0]) if abs(normal[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = _unit(np.cross(normal, ref))
    e2 = np.cross(normal, e1)
    parts = []
    for k in range(5):
        a = 2 * np.pi * k / 5 + rng.uniform(-0.1, 0.1)
        r = np.cos(a) * e1 + np.sin(a) * e2
        tt = np.cross(normal, r)
        sv = np.linspace(0, 1, 6)
        half = (np.sin(np.pi * (0.15 + 0.85 * sv)) * 0.45 * radius)[:, None]
        ctr = (centre + r[None] * (0.25 * radius + sv[:, None] * 0.75 * radius)
               + normal * 0.1 * radius * sv[:, None] ** 2)
        P = np.stack([ctr - tt * half, ctr, ctr + tt * half], 1)
        UV = np.stack(np.broadcast_arrays(sv[:, None], np.array([0.2, 0.5, 0.8])[None]), -1)
        parts.append(grid_mesh(P, UV, (0.95, 0.95, 0.92), layer=T.WHITE, cls=FLOWER, instance=idx))
    hh = np.linspace(0, 1, 6)
    disc = revolution_mesh(hh * 0.3 * radius, 0.35 * radius * np.sqrt(1 - hh**2), centre, normal, 10,
                           (0.95, 0.78, 0.1), layer=T.WHITE, cls=FLOWER, instance=idx)
    return [merge(parts), disc]


def _ok_above_pot(pts: np.ndarray, pot: Pot, margin: float = 0.3) -> bool:
    """True when no point is inside the pot wall/rim region or below the platform."""
    r = np.linalg.norm(pts[:, :2], axis=1)
    near_wall = (r > pot.top_radius - 0.8) & (r < pot.top_radius + pot.lip + 0.8)
    outside = r >= pot.top_radius + pot.lip + 0.8
    return bool(np.all(pts[:, 2] > 0.3) and np.all(pts[near_wall, 2] > pot.rim_z + margin)
                and np.all(pts[outside, 2] > pot.rim_z - 2.0))


def _hits_pot(pts: np.ndarray, pot: Pot, margin: float = 0.15) -> bool:
    """True when points lie inside the pot's wall/lip, below the soil inside the pot, or below the platform."""
    r = np.linalg.norm(pts[:, :2], axis=1)
    z = pts[:, 2]
    outer = np.where(z > pot.rim_z - 1.2, pot.top_radius + pot.lip, np.interp(z, [0, pot.height],
                                                                               [pot.bottom_radius, pot.top_radius]))
    inner = np.interp(z, [0, pot.height], [pot.bottom_radius, pot.top_radius]) - pot.wall
    below_rim = z < pot.rim_z + margin
    in_wall = below_rim & (r > inner - margin) & (r < outer + margin)
    in_soil = (r <= inner) & (z < pot.soil_z)
    return bool(np.any(in_wall) or np.any(in_soil) or np.any(z < 0.1))


def _draw_plant(rng: np.random.Generator, pot: Pot, avoid_azimuth: float | None, obstacle=None):
    soil = pot.soil_z
    crown = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), soil])
    crown_r = rng.uniform(1.0, 1.8)
    scale = rng.uniform(0.4, 1.6)
    n_leaves = int(rng.integers(5, 16))
    aniso = rng.uniform(0.12, 0.4)
    phi2, phi1, lop = rng.uniform(0, np.pi), rng.uniform(0, 2 * np.pi), rng.uniform(0.0, 0.2)
    meshes: list[Mesh] = []
    leaves = []
    golden = np.radians(137.5)
    az0 = rng.uniform(0, 2 * np.pi)
    tint_base = np.array([rng.uniform(0.8, 1.1), rng.uniform(0.85, 1.15), rng.uniform(0.7, 1.2)])
    for i in range(n_leaves):
        azim = az0 + i * golden + rng.normal(0, 0.25)
        reach = 1 + aniso * np.cos(2 * (azim - phi2)) + lop * np.cos(azim - phi1)
        age = i / max(n_leaves - 1, 1)  # 0 = oldest (outer, low), 1 = youngest (upright)
        L = 14.0 * scale * reach * rng.uniform(0.8, 1.15) * (1.05 - 0.3 * age)
        elev = np.radians(rng.uniform(35, 55) + 25 * age)
        leaflet_len = (4.5 + 3.2 * scale) * rng.uniform(0.85, 1.1) * (1.0 - 0.15 * age)
        tint = tint_base * (1.0 + 0.25 * (age - 0.5)) * rng.uniform(0.92, 1.08)
        senescence = rng.uniform(0.3, 0.9) if (age < 0.25 and rng.random() < 0.35) else 0.0
        for _ in range(10):
            parts, curve, bv, info = _leaf(rng, i, crown, crown_r, azim, L, elev, leaflet_len, pot, tint,
                                           senescence)
            far = np.linalg.norm(curve[:, :2], axis=1) > pot.top_radius - 0.8
            if _ok_above_pot(bv, pot) and _ok_above_pot(curve[far], pot) and not (
                    obstacle is not None and obstacle(np.concatenate([bv, curve]))):
                break
            elev = min(elev + np.radians(6), np.radians(85))
        meshes += parts
        leaves.append(info)
    # crown dome
    hh = np.linspace(0, 1, 8)
    meshes.append(revolution_mesh(hh * crown_r * 0.8, crown_r * np.sqrt(1 - hh**2 * 0.98), crown, Z, 14,
                                  (0.3, 0.24, 0.12), layer=T.WHITE, cls=CROWN, instance=0))
    # fruits
    n_fruits = int(rng.integers(1, 11))
    fruits = []
    for j in range(n_fruits):
        Lf = rng.uniform(2.2, 4.5) * (0.8 + 0.25 * scale)
        Rf = Lf * rng.uniform(0.36, 0.48)
        ripe = bool(rng.random() < 0.75)
        hanging = bool(rng.random() < 0.5)
        for _ in range(40):
            az = rng.uniform(0, 2 * np.pi)
            if avoid_azimuth is not None and abs((az - avoid_azimuth + np.pi) % (2 * np.pi) - np.pi) < np.radians(40):
                continue
            h = np.array([np.cos(az), np.sin(az), 0.0])
            base = crown + Z * 0.5 + h * crown_r * 0.4
            if hanging:
                r_out = pot.top_radius + pot.lip + Rf + rng.uniform(0.3, 1.5)
                up = pot.rim_z + rng.uniform(3, 8)
                end = h * r_out + Z * (pot.rim_z - rng.uniform(1.0, 6.0))
                P = np.stack([base, base * [1, 1, 0] + Z * up + h * 0.3 * pot.top_radius,
                              h * (r_out + 1.0) + Z * (up - 0.5), end])
                axis = _unit(-Z + h * rng.uniform(0.0, 0.25) + rng.normal(0, 0.08, 3))
            else:
                rr = rng.uniform(0.25, 0.6) * pot.top_radius
                end = h * rr + Z * (soil + Lf + rng.uniform(1.0, 6.0))
                P = np.stack([base, base + Z * (end[2] - base[2] + 2.5) + h * rr * 0.3, end + Z * 1.0])
                axis = _unit(-Z + rng.normal(0, 0.35, 3) * [1, 1, 0])
            for _ in range(10):
                curve = _bezier(P, 16)
                far = np.linalg.norm(curve[:, :2], axis=1) > pot.top_radius - 0.8
                if _ok_above_pot(curve[far & (np.arange(16) < 14)], pot, 0.2):
                    break
                P[1:-1, 2] += 1.0
            parts = _fruit(rng, j, curve[-1], axis, Lf, Rf, ripe)
            body = np.concatenate([m.v for m in parts])
            if not _hits_pot(body, pot) and not (obstacle is not None and obstacle(np.concatenate([body, curve]))):
                break
        meshes.append(tube_mesh(curve, np.linspace(0.12, 0.08, 16), 5, (0.3, 0.42, 0.15), uv_scale=0.05,
                                layer=T.WHITE, cls=PEDUNCLE, instance=j))
        meshes += parts
        fruits.append(dict(attach=curve[-1].tolist(), tip=(curve[-1] + axis * Lf).tolist(), length_cm=float(Lf),
                           radius_cm=float(Rf), ripe=ripe, hanging_over_rim=hanging,
                           azimuth_deg=float(np.degrees(az) % 360)))
    # flowers
    n_flowers = int(rng.choice(4, p=[0.35, 0.3, 0.2, 0.15]))
    flowers = []
    for k in range(n_flowers):
        az = rng.uniform(0, 2 * np.pi)
        h = np.array([np.cos(az), np.sin(az), 0.0])
        top = crown + h * rng.uniform(0.3, 0.8) * pot.top_radius + Z * rng.uniform(5, 12) * (0.7 + 0.4 * scale)
        curve = _bezier(np.stack([crown + Z * 0.5, crown + Z * (top[2] - crown[2]) * 1.1, top]), 12)
        rad = rng.uniform(0.9, 1.4)
        normal = _unit(Z * rng.uniform(0.5, 1.0) + h * rng.uniform(0.2, 0.8))
        meshes.append(tube_mesh(curve, 0.08, 5, (0.3, 0.42, 0.15), uv_scale=0.05, layer=T.WHITE, cls=PEDUNCLE,
                                instance=n_fruits + k))
        meshes += _flower(rng, k, top, normal, rad)
        flowers.append(dict(centre=top.tolist(), radius_cm=float(rad)))
    info = dict(n_leaves=n_leaves, n_fruits=n_fruits, n_flowers=n_flowers, crown_xyz=crown.tolist(),
                crown_radius_cm=float(crown_r), size_scale=float(scale), anisotropy=float(aniso),
                leaves=leaves, fruits=fruits, flowers=flowers)
    return meshes, info


def plant_vertices(meshes: list[Mesh]) -> np.ndarray:
    return np.concatenate([m.v for m in meshes])


def make_plant(rng: np.random.Generator, pot: Pot, avoid_azimuth: float | None = None, obstacle=None,
               max_tries: int = 30):
    """Draw a plant whose height and width1 fall in the target ranges. Returns ``(meshes, info)``.

    ``avoid_azimuth`` (radians) keeps hanging fruit away from the cube's side of the pot;
    ``obstacle(points [N, 3]) -> bool`` says whether points collide with something else (the cube).
    """
    best = None
    for attempt in range(max_tries):
        meshes, info = _draw_plant(rng, pot, avoid_azimuth, obstacle)
        v = plant_vertices(meshes)
        hgt, (w1, _) = plant_height(v), pca_widths(v)
        miss = max(0, HEIGHT_RANGE[0] - hgt, hgt - HEIGHT_RANGE[1]) + max(0, WIDTH1_RANGE[0] - w1, w1 - WIDTH1_RANGE[1])
        info["draws"] = attempt + 1
        if best is None or miss < best[0]:
            best = (miss, meshes, info)
        if miss == 0:
            break
    return best[1], best[2]

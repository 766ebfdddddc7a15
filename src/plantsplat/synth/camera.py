"""Phone camera: intrinsics and a continuous three-ring path with smooth handheld jitter.

Conventions (the same as ``ground_truth.json``):

- ``c2w`` is a camera-to-world 4x4 in OpenCV camera axes (x right, y down, z forward), cm;
- pixel (u, v) has its centre at integer coordinates (OpenCV), so a centred principal point is
  ``((W - 1) / 2, (H - 1) / 2)``; ``K`` maps camera coordinates to those pixel coordinates.

The operator walks three loops around the plant: low (0-5 cm above the soil), mid (5-20 cm) and high
(20-50 cm), in random order direction and start angle, moving smoothly between rings, always looking
at the plant, with smooth position and orientation jitter.

Example:
    >>> import numpy as np
    >>> K = intrinsics(540, 960, 66.0)
    >>> K["cx"], K["cy"]
    (269.5, 479.5)
"""

from __future__ import annotations

import numpy as np

RINGS = {"low": (0.0, 5.0), "mid": (5.0, 20.0), "high": (20.0, 50.0)}
"""Camera height above the soil surface for each ring (cm), as in the paper."""


FOV_LONG_RANGE_DEG = (62.0, 72.0)
"""Field of view across the long side of the frame, drawn per seed (phone main cameras)."""


def framing_distance(reach: float, fov_short_deg: float, factor: float = 1.0) -> float:
    """Camera distance (cm) from the pot axis that frames ``reach`` cm around it across the short side."""
    d = (0.85 * reach + 3.0) / np.tan(np.radians(fov_short_deg) / 2) * factor
    return float(np.clip(d, 30.0, 160.0))


def max_distance(reach: float) -> float:
    """An upper bound of :func:`framing_distance` over every frame shape and seed (for room layout)."""
    return framing_distance(reach, 30.0, 1.05) + 3.0


def intrinsics(width: int, height: int, fov_long_deg: float) -> dict:
    """Pinhole intrinsics with square pixels; ``fov_long_deg`` is the field of view across the long side."""
    f = 0.5 * max(width, height) / np.tan(np.radians(fov_long_deg) / 2)
    return dict(width=int(width), height=int(height), fx=float(f), fy=float(f), cx=(width - 1) / 2,
                cy=(height - 1) / 2, model="PINHOLE")


def K_matrix(intr: dict) -> np.ndarray:
    return np.array([[intr["fx"], 0, intr["cx"]], [0, intr["fy"], intr["cy"]], [0, 0, 1.0]])


def look_at(eye: np.ndarray, target: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """Camera-to-world (OpenCV axes) at ``eye`` looking at ``target``, rolled by ``roll`` radians."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(roll), np.sin(roll)
    x, y = c * x + s * y, -s * x + c * y
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = eye
    return T


def smooth_noise(rng: np.random.Generator, t: np.ndarray, n_waves: int = 4, period=(0.15, 0.6)) -> np.ndarray:
    """A smooth zero-mean signal of unit-ish amplitude over ``t`` in [0, 1] (sum of random sinusoids)."""
    out = np.zeros_like(t)
    for _ in range(n_waves):
        p = rng.uniform(*period)
        out += np.sin(2 * np.pi * t / p + rng.uniform(0, 2 * np.pi)) * rng.uniform(0.5, 1.0)
    return out / np.sqrt(n_waves / 2)


def camera_path(rng: np.random.Generator, n: int, soil_z: float, plant_height: float, reach: float,
                fov_short_deg: float, shake: float = 1.0) -> tuple[list[np.ndarray], list[str], dict]:
    """``n`` camera-to-world poses circling the plant three times (one loop per ring).

    ``reach`` is the horizontal radius (cm) around the pot axis that must stay in view (plant and
    cube). Returns ``(c2w list, ring label per frame, path parameters)``; the label is the ring whose
    height band contains the camera's height above the soil. ``shake`` scales the hand-held jitter.
    """
    heights = {"low": rng.uniform(1.0, 4.0), "mid": rng.uniform(8.0, 17.0), "high": rng.uniform(25.0, 45.0)}
    order = ["low", "mid", "high"] if rng.random() < 0.5 else ["high", "mid", "low"]
    direction = 1.0 if rng.random() < 0.5 else -1.0
    az0 = rng.uniform(0, 2 * np.pi)
    dist = framing_distance(reach, max(fov_short_deg, 30.0), rng.uniform(0.92, 1.05))
    t = (np.arange(n) + 0.5) / n  # [n] in (0, 1)
    seg = np.minimum((t * 3).astype(int), 2)
    local = t * 3 - seg  # progress inside the ring
    hs = np.array([heights[r] for r in order])
    # smooth transition over the last 20 % of each ring
    h = hs[seg].copy()
    trans = np.clip((local - 0.8) / 0.2, 0, 1)
    nxt = np.minimum(seg + 1, 2)
    w = trans * trans * (3 - 2 * trans)
    h = (1 - w) * h + w * hs[nxt]
    speed = 1.0 + 0.08 * smooth_noise(rng, t, 3, (0.2, 0.5))
    az = az0 + direction * 2 * np.pi * 3 * np.cumsum(speed) / np.sum(speed)
    # closer on the high ring (looking down), farther on the low ring
    r_ring = {"low": dist * rng.uniform(0.95, 1.1), "mid": dist, "high": dist * rng.uniform(0.85, 1.0)}
    rr = np.array([r_ring[r] for r in order])
    radius = (1 - w) * rr[seg] + w * rr[nxt]
    jit = rng.uniform(0.5, 2.0) * shake  # cm
    rot_jit = np.radians(rng.uniform(0.5, 2.0) * shake)
    eye = np.stack([radius * np.cos(az), radius * np.sin(az), soil_z + h], 1)
    eye += jit * np.stack([smooth_noise(rng, t) for _ in range(3)], 1)
    aim_z = soil_z + plant_height * np.interp(h, [0, 45], [0.4, 0.1])
    target = np.stack([np.zeros(n), np.zeros(n), aim_z], 1)
    target += (dist * np.tan(rot_jit)) * np.stack([smooth_noise(rng, t) for _ in range(3)], 1)
    roll = rot_jit * 1.5 * smooth_noise(rng, t)
    c2w = [look_at(eye[i], target[i], roll[i]) for i in range(n)]
    labels = ["low" if x < RINGS["low"][1] else "mid" if x < RINGS["mid"][1] else "high" for x in eye[:, 2] - soil_z]
    params = dict(ring_heights_above_soil_cm=heights, ring_order=order, direction="ccw" if direction > 0 else "cw",
                  start_azimuth_deg=float(np.degrees(az0) % 360), distance_cm=dist, ring_radius_cm=r_ring,
                  position_jitter_cm=float(jit), rotation_jitter_deg=float(np.degrees(rot_jit)))
    return c2w, labels, params

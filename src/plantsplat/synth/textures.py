"""Procedural textures (one texture-array layer each, 512 x 512 RGB) for the synthetic scene.

Textures vary with the seed: wood or tile floors, painted or papered walls with posters, cardboard,
fabric, printed packaging (with text), green decoys (so that background removal cannot threshold
green), leaf venation, strawberry achenes, soil with perlite, and the six ArUco faces of the cube.

Example:
    >>> import numpy as np
    >>> layers = make_layers(np.random.default_rng(0), size=64)
    >>> layers.shape[1:], layers.dtype
    ((64, 64, 3), dtype('uint8'))
"""

from __future__ import annotations

import colorsys

import cv2
import numpy as np

from plantsplat.cube import CubeSpec, marker_image

SIZE = 512
# layer indices
WHITE = 0
MARKER0 = 1  # 1..6: cube faces in plantsplat.cube.FACE_NAMES order
LEAF_TOP, LEAF_BOTTOM, FRUIT, SOIL, FLOOR, WALL_A, WALL_B, CARDBOARD, FABRIC, PRINT, WOOD, POT, PLATFORM, \
    GREEN_DECOY, POSTER, CHECKER, FOLIAGE_PRINT = range(7, 24)
N_LAYERS = 24
MARKER_FACE_TEXELS = 500
"""The cube face spans texels [6, 506) of its layer; the marker spans [16, 496) (9.6 cm of 10 cm)."""


def _noise(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """Smooth value noise in [0, 1] with about ``cells`` blobs per side. ``[size, size]``."""
    g = rng.random((cells + 3, cells + 3)).astype(np.float32)
    up = cv2.resize(g, (size * (cells + 3) // cells,) * 2, interpolation=cv2.INTER_CUBIC)
    o = size // cells
    return np.clip(up[o:o + size, o:o + size], 0, 1)


def _fbm(rng, size, base=4, octaves=4) -> np.ndarray:
    acc = np.zeros((size, size), np.float32)
    amp, tot = 1.0, 0.0
    for k in range(octaves):
        acc += amp * _noise(rng, size, min(base * 2 ** k, size // 2))
        tot += amp
        amp *= 0.5
    return acc / tot


def _tint(gray: np.ndarray, c0, c1) -> np.ndarray:
    c0, c1 = np.asarray(c0, np.float32), np.asarray(c1, np.float32)
    return gray[..., None] * (c1 - c0) + c0


def _to_u8(img: np.ndarray) -> np.ndarray:
    return np.clip(img * 255 + 0.5, 0, 255).astype(np.uint8)


def _rand_colour(rng, sat=(0.3, 0.9), val=(0.3, 0.95), hue=None) -> np.ndarray:
    h = rng.random() if hue is None else hue
    return np.array(colorsys.hsv_to_rgb(h, rng.uniform(*sat), rng.uniform(*val)), np.float32)


def _draw_text(img, rng, n, scale=(0.6, 2.0), colour=None):
    words = ["PLANT", "SOIL", "BIO", "LAB", "GROW", "NO.", "FRAGILE", "2025", "MIX", "Ag", "STORE", "BOX",
             "SEED", "FOOD", "KEEP DRY", "THIS SIDE UP", "TRAY", "A-12", "Q7"]
    h, w = img.shape[:2]
    for _ in range(n):
        c = (255 * (colour if colour is not None else _rand_colour(rng, val=(0.05, 0.6)))).tolist()
        txt = " ".join(rng.choice(words, size=rng.integers(1, 3)))
        cv2.putText(img, txt, (int(rng.integers(0, w - 60)), int(rng.integers(20, h))), int(rng.integers(0, 8)),
                    float(rng.uniform(*scale)), c, int(rng.integers(1, 4)), cv2.LINE_AA)


def _shapes(img, rng, n, palette=None):
    h, w = img.shape[:2]
    for _ in range(n):
        c = (255 * (palette[rng.integers(len(palette))] if palette is not None else _rand_colour(rng))).tolist()
        k = rng.integers(3)
        p = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        if k == 0:
            cv2.circle(img, p, int(rng.integers(6, w // 6)), c, -1 if rng.random() < 0.6 else 3, cv2.LINE_AA)
        elif k == 1:
            q = (p[0] + int(rng.integers(-w // 4, w // 4)), p[1] + int(rng.integers(-h // 4, h // 4)))
            cv2.rectangle(img, p, q, c, -1 if rng.random() < 0.6 else 3, cv2.LINE_AA)
        else:
            pts = rng.integers(0, w, size=(3, 2)).astype(np.int32)
            cv2.fillPoly(img, [pts], c, cv2.LINE_AA)


def marker_face(marker_id: int, size: int = SIZE, cube: CubeSpec = CubeSpec()) -> np.ndarray:
    """White cube face with its marker: face texels [6, 506), marker texels [16, 496) (for ``size`` 512)."""
    img = np.full((size, size, 3), 255, np.uint8)
    s = size / SIZE
    face = int(round(MARKER_FACE_TEXELS * s))
    mpx = int(round(face * cube.marker_size / cube.size))
    o = (size - mpx) // 2
    img[o:o + mpx, o:o + mpx] = marker_image(marker_id, mpx, cube)[..., None]
    return img


def make_layers(rng: np.random.Generator, size: int = SIZE, cube: CubeSpec = CubeSpec()) -> np.ndarray:
    """All texture layers for one seed: ``[N_LAYERS, size, size, 3]`` uint8 (sRGB)."""
    L = np.zeros((N_LAYERS, size, size, 3), np.float32)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) / size
    L[WHITE] = 1.0
    # leaf: midrib along v = 0.5 (image x = u along the midrib, y = v across), pinnate veins, fine noise
    for layer, base in ((LEAF_TOP, 1.0), (LEAF_BOTTOM, 1.25)):
        n = _fbm(rng, size, 8, 4)
        across = np.abs(yy - 0.5)
        vein_phase = (xx * 9 - across * 6) % 1.0
        veins = np.exp(-((vein_phase - 0.5) ** 2) / 0.004) * (across > 0.03)
        mid = np.exp(-(across**2) / 0.0006)
        g = 0.78 + 0.22 * n + 0.22 * veins + 0.35 * mid
        L[layer] = np.clip(g * base, 0, 1.3)[..., None] * np.array([1, 1, 1], np.float32) / 1.3
        if layer == LEAF_TOP:  # darker intervein texture
            L[layer] *= (0.85 + 0.15 * _noise(rng, size, 40))[..., None]
    # strawberry: red base with yellow achenes in a staggered lattice (u around, v along the fruit)
    fr = np.ones((size, size, 3), np.float32)
    step = size // 12
    for r in range(0, size + step, step):
        off = (r // step % 2) * step // 2
        for c in range(-step, size + step, step):
            p = (c + off + int(rng.integers(-3, 4)), r + int(rng.integers(-3, 4)))
            cv2.ellipse(fr, p, (max(2, step // 8), max(2, step // 6)), 0, 0, 360, (0.35, 0.32, 0.12), -1, cv2.LINE_AA)
            cv2.ellipse(fr, p, (max(1, step // 14), max(2, step // 9)), 0, 0, 360, (1.0, 0.95, 0.45), -1, cv2.LINE_AA)
    L[FRUIT] = fr * (0.9 + 0.1 * _noise(rng, size, 16))[..., None]
    # soil with perlite and small stones
    n = _fbm(rng, size, 16, 4)
    L[SOIL] = _tint(n, (0.08, 0.055, 0.04), (0.3, 0.22, 0.15))
    for _ in range(int(rng.integers(60, 160))):
        p = (int(rng.integers(size)), int(rng.integers(size)))
        v = float(rng.uniform(0.7, 0.95))
        cv2.circle(L[SOIL], p, int(rng.integers(2, 7)), (v, v, v * 0.97), -1, cv2.LINE_AA)
    # floor: wood planks, tiles or speckled vinyl
    kind = rng.integers(3)
    if kind == 0:
        c0, c1 = _rand_colour(rng, (0.3, 0.6), (0.25, 0.45), hue=rng.uniform(0.05, 0.1)), \
            _rand_colour(rng, (0.3, 0.6), (0.5, 0.8), hue=rng.uniform(0.05, 0.12))
        grain = _noise(rng, size, 6)
        rows = (yy * 4).astype(int)
        plank = np.sin((xx * 3 + grain * 2 + rows * 0.37) * 40) * 0.5 + 0.5
        g = 0.6 * plank + 0.4 * _fbm(rng, size, 8)
        img = _tint(g, c0, c1)
        img[(yy * 4 % 1.0) < 0.012] *= 0.45
        L[FLOOR] = img
    elif kind == 1:
        c0 = _rand_colour(rng, (0.0, 0.4), (0.5, 0.9))
        c1 = _rand_colour(rng, (0.0, 0.6), (0.2, 0.7))
        chk = ((xx * 4).astype(int) + (yy * 4).astype(int)) % 2
        img = np.where(chk[..., None] == 1, c0, c1) * (0.85 + 0.15 * _fbm(rng, size, 8))[..., None]
        grout = ((xx * 4 % 1.0) < 0.015) | ((yy * 4 % 1.0) < 0.015)
        img[grout] = 0.55
        L[FLOOR] = img
    else:
        base = _rand_colour(rng, (0.0, 0.3), (0.3, 0.7))
        img = base * (0.8 + 0.2 * _fbm(rng, size, 16))[..., None]
        spk = rng.random((size, size)) < 0.02
        img[spk] = img[spk] * 0.4 + 0.6 * rng.random((int(spk.sum()), 1))
        L[FLOOR] = img
    # walls: painted plaster, one of them with a paper pattern
    for layer in (WALL_A, WALL_B):
        base = _rand_colour(rng, (0.0, 0.35), (0.6, 0.95))
        img = base * (0.88 + 0.12 * _fbm(rng, size, 6))[..., None]
        if layer == WALL_B and rng.random() < 0.6:
            stripes = ((xx * rng.integers(6, 16)) % 1.0) < 0.5
            img[stripes] *= rng.uniform(0.8, 0.93)
        L[layer] = img
    # cardboard with printed labels
    img = _tint(_fbm(rng, size, 8), (0.55, 0.4, 0.25), (0.75, 0.58, 0.38))
    img[(np.abs(yy - 0.5) < 0.03)] *= 0.8  # tape
    img_u8 = _to_u8(img)
    _draw_text(img_u8, rng, int(rng.integers(3, 8)))
    L[CARDBOARD] = img_u8 / 255.0
    # fabric: stripes/checks
    c0, c1 = _rand_colour(rng), _rand_colour(rng)
    k = rng.integers(4, 14)
    pattern = (((xx * k) % 1.0) < 0.5) ^ (((yy * k) % 1.0) < 0.3 * rng.random())
    L[FABRIC] = np.where(pattern[..., None], c0, c1) * (0.85 + 0.15 * _noise(rng, size, 64))[..., None]
    # packaging print: shapes and text on a coloured ground
    img_u8 = _to_u8(np.broadcast_to(_rand_colour(rng, val=(0.6, 1.0)), (size, size, 3)).copy())
    _shapes(img_u8, rng, int(rng.integers(10, 30)))
    _draw_text(img_u8, rng, int(rng.integers(4, 10)))
    L[PRINT] = img_u8 / 255.0
    # furniture wood
    grain = _noise(rng, size, 4)
    g = 0.5 + 0.5 * np.sin((yy * 30 + grain * 4) * 2 * np.pi * rng.uniform(0.5, 1.5))
    L[WOOD] = _tint(0.6 * g + 0.4 * _fbm(rng, size, 16), (0.35, 0.22, 0.12), (0.62, 0.45, 0.28))
    # pot (slightly mottled), platform plastic
    L[POT] = (0.9 + 0.1 * _fbm(rng, size, 8, 3))[..., None] * np.ones(3, np.float32)
    L[PLATFORM] = (0.88 + 0.12 * _fbm(rng, size, 16, 3))[..., None] * np.ones(3, np.float32)
    # green decoy objects: a green plastic surface and a print with leaf shapes
    g = _rand_colour(rng, (0.5, 0.9), (0.35, 0.7), hue=rng.uniform(0.25, 0.4))
    L[GREEN_DECOY] = g * (0.85 + 0.15 * _fbm(rng, size, 8))[..., None]
    img_u8 = _to_u8(np.broadcast_to(_rand_colour(rng, (0.0, 0.3), (0.75, 1.0)), (size, size, 3)).copy())
    for _ in range(int(rng.integers(15, 40))):
        c = _rand_colour(rng, (0.5, 1.0), (0.25, 0.7), hue=rng.uniform(0.22, 0.42)).tolist()
        p = (int(rng.integers(size)), int(rng.integers(size)))
        ax = (int(rng.integers(15, 60)), int(rng.integers(6, 25)))
        cv2.ellipse(img_u8, p, ax, float(rng.uniform(0, 180)), 0, 360, [255 * x for x in c], -1, cv2.LINE_AA)
    L[FOLIAGE_PRINT] = img_u8 / 255.0
    # posters: shapes and text
    img_u8 = _to_u8(np.broadcast_to(_rand_colour(rng, val=(0.7, 1.0)), (size, size, 3)).copy())
    _shapes(img_u8, rng, int(rng.integers(15, 40)))
    _draw_text(img_u8, rng, int(rng.integers(2, 6)), scale=(1.0, 3.0))
    L[POSTER] = img_u8 / 255.0
    c0, c1 = _rand_colour(rng), _rand_colour(rng)
    chk = ((xx * 8).astype(int) + (yy * 8).astype(int)) % 2
    L[CHECKER] = np.where(chk[..., None] == 1, c0, c1)
    out = _to_u8(L)
    for i, mid in enumerate(cube.face_ids):
        out[MARKER0 + i] = marker_face(mid, size, cube)
    return out

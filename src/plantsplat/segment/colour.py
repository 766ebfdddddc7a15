"""Plant colour models: per-pixel classes for leaves, petioles, fruit and flowers.

Two levels per class, used with hysteresis by the segmenter: *strong* pixels are almost surely
plant tissue (they seed the plant), *weak* pixels are accepted only where they touch strong ones.

- green tissue (leaves of every shade, petioles, calyx, unripe fruit): Meyer & Neto's excess green
  minus excess red index ``ExG - ExR`` on chromatic coordinates (a standard vegetation index, robust
  to shading), restricted to the hue range of foliage (yellow-green to teal) and a minimum
  brightness so that near-black noise is not classified;
- red/pink fruit: high-saturation red hue (HSV), which excludes brownish soil and pale pots;
- white/cream flowers and yellow flower centres: only weak (they are also the colour of walls and
  of the cube) and thus accepted only next to strong plant tissue;
- stems (:func:`stem_colour_mask`): saturated olive, brown and red-brown (petiole bases, peduncles,
  runners), which soil, wood and terracotta share; the segmenter accepts them only as thin runs
  attached to the plant.

Example:
    >>> import numpy as np
    >>> img = np.zeros((4, 4, 3), np.uint8); img[:2] = (40, 140, 40)   # green top half
    >>> strong, weak, pale = plant_colour_masks(img)
    >>> bool(strong[0, 0]), bool(strong[3, 3])
    (True, False)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ColourModel:
    """Thresholds of the plant colour classes (OpenCV HSV: H in [0, 180), S and V in [0, 255])."""

    exgr_strong: float = 0.08
    """ExG - ExR above this (and foliage hue) = strong green tissue."""
    exgr_weak: float = -0.02
    """ExG - ExR above this (and foliage hue) = weak green tissue."""
    green_hue: tuple[int, int] = (22, 100)
    """Foliage hue range (OpenCV units; 22 = 44 deg yellow-green, 100 = 200 deg teal)."""
    min_value: int = 28
    """Pixels darker than this (HSV V) are never plant colour (noise, deep shadow)."""
    min_sat_green: int = 100
    """Strong green needs at least this saturation (living leaves are saturated; painted walls are not)."""
    min_sat_weak: int = 45
    """Weak green needs at least this saturation."""
    red_hue: tuple[int, int] = (6, 165)
    """Red fruit: hue at most the first or at least the second value (terracotta and soil, 8-15, are out)."""
    red_sat_strong: int = 120
    red_value_strong: int = 90
    """Strong red needs at least this brightness (dark maroon/purple walls and their noise are not fruit)."""
    red_sat_weak: int = 70
    white_sat: int = 50
    """Weak white (flowers): saturation at most this and value at least ``white_value``."""
    white_value: int = 165
    stem_hue: tuple[int, int] = (5, 30)
    """Stem colours: hue in this range (red-brown to olive; it overlaps the foliage hues, where brownish olive fails the
    ExG - ExR test)..."""
    stem_sat: int = 100
    """...with at least this saturation (and ``min_value``): grey-brown dust and shadows are not stems."""
    unripe_hue: tuple[int, int] = (18, 45)
    """Unripe fruit (:func:`unripe_colour_mask`): pale yellow-green to cream, hue in this range..."""
    unripe_sat: tuple[int, int] = (35, 150)
    """...saturation in this range (paler than leaves, more coloured than white walls)..."""
    unripe_value: int = 60
    """...and at least this brightness."""


def plant_colour_masks(
    rgb: np.ndarray, model: ColourModel = ColourModel(), with_red: bool = False
) -> tuple[np.ndarray, ...]:
    """Plant-colour masks of an RGB uint8 image ``[H, W, 3]`` -> ``(strong, weak, pale)``, bool ``[H, W]``.

    ``strong``: green tissue and red fruit; ``weak`` (includes ``strong``): paler or darker green and
    red; ``pale``: white/cream (flowers, unripe fruit), which the segmenter accepts only as small blobs
    touching the plant. Red fruit needs its strong colour over a 3x3 neighbourhood (isolated noise
    pixels of dark red walls are not fruit). With ``with_red`` a fourth mask is returned: ``red_only``,
    the weak pixels that are red and not green, which the segmenter grows only from strong red.

    Example:
        >>> import numpy as np
        >>> s, w, p = plant_colour_masks(np.full((2, 2, 3), (200, 30, 40), np.uint8))  # strawberry red
        >>> bool(s.all()), bool(w.all()), bool(p.any())
        (True, True, False)
    """
    import cv2

    rgb = np.ascontiguousarray(rgb)
    hsv = cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV)  # [H, W, 3] uint8
    h, s, v = hsv[..., 0], hsv[..., 1], hsv[..., 2]
    f = rgb.astype(np.float32)
    tot = f.sum(axis=2) + 1e-3
    r, g, b = f[..., 0] / tot, f[..., 1] / tot, f[..., 2] / tot
    exgr = (2 * g - r - b) - (1.4 * r - g)  # ExG - ExR, [H, W]
    bright = v >= model.min_value
    hue_green = (h >= model.green_hue[0]) & (h <= model.green_hue[1])
    green_strong = (exgr > model.exgr_strong) & hue_green & (s >= model.min_sat_green) & bright
    green_weak = (exgr > model.exgr_weak) & hue_green & (s >= model.min_sat_weak) & bright
    hue_red = (h <= model.red_hue[0]) | (h >= model.red_hue[1])
    red_strong = hue_red & (s >= model.red_sat_strong) & (v >= model.red_value_strong)
    k3 = np.ones((3, 3), np.uint8)
    red_strong = cv2.morphologyEx(red_strong.astype(np.uint8), cv2.MORPH_OPEN, k3).astype(bool)
    red_weak = hue_red & (s >= model.red_sat_weak) & bright
    white = (s <= model.white_sat) & (v >= model.white_value)
    strong = green_strong | red_strong
    weak = strong | green_weak | red_weak
    pale = white & ~weak
    if with_red:
        return strong, weak, pale, red_weak & ~green_weak & ~green_strong
    return strong, weak, pale


def unripe_colour_mask(rgb: np.ndarray, model: ColourModel = ColourModel()) -> np.ndarray:
    """Pixels of an RGB uint8 image ``[H, W, 3]`` that could be unripe fruit: pale yellow-green to cream
    (``model.unripe_*``), bool ``[H, W]``. Beige walls, wood and boxes share it: the segmenter uses it only where a
    fruit-sized piece of the plant's volume shows this colour from most of the orbit.

    Example:
        >>> import numpy as np
        >>> bool(unripe_colour_mask(np.full((1, 1, 3), (190, 196, 140), np.uint8))[0, 0])  # unripe strawberry
        True
        >>> bool(unripe_colour_mask(np.full((1, 1, 3), (40, 140, 40), np.uint8))[0, 0])  # leaf
        False
    """
    return _hsv_box(rgb, (model.unripe_hue[0], model.unripe_sat[0], model.unripe_value),
                    (model.unripe_hue[1], model.unripe_sat[1], 255))


def stem_colour_mask(rgb: np.ndarray, model: ColourModel = ColourModel()) -> np.ndarray:
    """Stem-coloured pixels of an RGB uint8 image ``[H, W, 3]``: saturated olive, brown or red-brown
    (``model.stem_hue``, ``model.stem_sat``, ``model.min_value``), bool ``[H, W]``.

    Example:
        >>> import numpy as np
        >>> bool(stem_colour_mask(np.full((1, 1, 3), (70, 55, 18), np.uint8))[0, 0])  # brown petiole base
        True
        >>> bool(stem_colour_mask(np.full((1, 1, 3), (120, 110, 100), np.uint8))[0, 0])  # grey-brown
        False
    """
    return _hsv_box(rgb, (model.stem_hue[0], model.stem_sat, model.min_value), (model.stem_hue[1] - 1, 255, 255))


def _hsv_box(rgb: np.ndarray, lo: tuple[int, int, int], hi: tuple[int, int, int]) -> np.ndarray:
    """Pixels of an RGB uint8 image whose OpenCV HSV (hue 0-179) lies in the box ``lo``..``hi`` (both inclusive)."""
    import cv2

    hsv = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2HSV)
    return cv2.inRange(hsv, np.array(lo, np.uint8), np.array(hi, np.uint8)) > 0

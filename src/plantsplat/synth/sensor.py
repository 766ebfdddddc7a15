"""Phone-camera image formation applied to the rendered linear radiance.

Per seed: a base exposure (set once from the first frame), a smooth exposure drift of a few tenths
of a stop and a slight white-balance drift, vignetting, per-frame motion blur along the image-space
motion (a line kernel, an approximation of a finite shutter), signal-dependent sensor noise (shot +
read noise), a soft highlight shoulder and sRGB encoding to 8 bits. H.264 compression of the video is
the last degradation (see :mod:`plantsplat.synth.video`); the PNG frames are the same images before it.

Example:
    >>> import numpy as np
    >>> s = SensorModel.draw(np.random.default_rng(0), n_frames=10, clean=False)
    >>> img = s.develop(np.full((4, 4, 3), 0.2, np.float32), 0, np.random.default_rng(1), blur_dir=(1, 0))
    >>> img.dtype, img.shape
    (dtype('uint8'), (4, 4, 3))
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from plantsplat.synth.camera import smooth_noise

_LUT_SIZE = 65536
_LUT_SCALE = (_LUT_SIZE - 1) / 2.0  # linear values in [0, 2]
_LUT: list[np.ndarray] = []


def _tone_lut() -> np.ndarray:
    """uint8 sRGB output for linear input ``i / _LUT_SCALE``: ``x (1 + x / 4) / (1 + x)``, then sRGB."""
    if not _LUT:
        x = np.arange(_LUT_SIZE, dtype=np.float64) / _LUT_SCALE
        y = np.minimum(x * (1 + x / 4.0) / (1 + x), 1.0)
        srgb = np.where(y <= 0.0031308, 12.92 * y, 1.055 * np.power(y, 1 / 2.4) - 0.055)
        _LUT.append((srgb * 255 + 0.5).clip(0, 255).astype(np.uint8))
    return _LUT[0]


@dataclass
class SensorModel:
    exposure_ev: np.ndarray  # [n] drift in stops around the base exposure
    wb: np.ndarray  # [n, 3] white-balance gains
    blur_px: np.ndarray  # [n] motion blur length (pixels)
    shot: float  # shot-noise variance per unit linear signal
    read: float  # read-noise standard deviation (linear)
    vignette: float  # relative fall-off at the image corner
    base_gain: float = 1.0  # set by calibrate()

    @classmethod
    def draw(cls, rng: np.random.Generator, n_frames: int, clean: bool = False, hard: bool = False) -> SensorModel:
        """A seed's sensor; ``hard``: exposure drift 2.5 times as large (up to about a stop)."""
        t = (np.arange(n_frames) + 0.5) / max(n_frames, 1)
        if clean:
            return cls(np.zeros(n_frames), np.ones((n_frames, 3)), np.zeros(n_frames), 0.0, 0.0, 0.0)
        amp = rng.uniform(0.08, 0.35) * (2.5 if hard else 1.0)
        ev = amp * smooth_noise(rng, t, 3, (0.3, 1.0))
        wb = 1.0 + rng.uniform(0.01, 0.04) * np.stack([smooth_noise(rng, t, 2, (0.4, 1.2)) for _ in range(3)], 1)
        max_blur = rng.uniform(0.5, 3.0)
        blur = max_blur * (0.5 + 0.5 * smooth_noise(rng, t, 4, (0.05, 0.3))).clip(0, 1)
        return cls(ev, wb, blur, shot=float(rng.uniform(2e-4, 1.2e-3)), read=float(rng.uniform(0.002, 0.006)),
                   vignette=float(rng.uniform(0.1, 0.3)))

    def calibrate(self, linear: np.ndarray, target: float = 0.2) -> None:
        """Auto-exposure once per capture: the frame's median luminance maps to ``target``."""
        lum = linear @ np.array([0.2126, 0.7152, 0.0722], np.float32)
        med = np.nanmedian(lum)
        self.base_gain = float(target / max(med, 1e-4)) if np.isfinite(med) else 1.0

    def settings(self) -> dict:
        return dict(base_gain=self.base_gain, exposure_drift_ev_max=float(np.abs(self.exposure_ev).max(initial=0)),
                    white_balance_drift_max=float(np.abs(self.wb - 1).max(initial=0)),
                    motion_blur_px_max=float(self.blur_px.max(initial=0)), shot_noise_var=self.shot,
                    read_noise_std=self.read, vignette=self.vignette, tone="soft shoulder + sRGB, 8 bit",
                    motion_blur_model="line kernel along the image motion of the pot axis, length per frame")

    def develop(self, linear: np.ndarray, i: int, rng: np.random.Generator, blur_dir=(1.0, 0.0)) -> np.ndarray:
        """Linear radiance ``[H, W, 3]`` float32 of frame ``i`` -> sRGB uint8 ``[H, W, 3]``."""
        gain = np.float32(self.base_gain * 2.0 ** self.exposure_ev[i]) * self.wb[i].astype(np.float32)  # [3]
        img = np.nan_to_num(linear, nan=0.0, posinf=0.0, neginf=0.0) * gain
        H, W = img.shape[:2]
        L = float(self.blur_px[i])
        if L > 0.25:
            k = int(np.ceil(L)) * 2 + 1
            ker = np.zeros((k, k), np.float32)
            d = np.asarray(blur_dir, float)
            d = d / max(np.linalg.norm(d), 1e-9)
            c = k // 2
            for s in np.linspace(-L / 2, L / 2, 4 * k):
                x, y = c + s * d[0], c + s * d[1]
                x0, y0 = int(np.floor(x)), int(np.floor(y))
                fx, fy = x - x0, y - y0
                for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy),
                                  (1, 1, fx * fy)):
                    if 0 <= x0 + dx < k and 0 <= y0 + dy < k:
                        ker[y0 + dy, x0 + dx] += w
            img = cv2.filter2D(img, -1, ker / ker.sum(), borderType=cv2.BORDER_REFLECT)
        if self.vignette > 0:
            if getattr(self, "_vig", None) is None or self._vig.shape != (H, W, 1):
                yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
                r2 = ((xx - W / 2) ** 2 + (yy - H / 2) ** 2) / ((W / 2) ** 2 + (H / 2) ** 2)
                self._vig = (1 - self.vignette * r2)[..., None].astype(np.float32)
            img *= self._vig
        if self.shot > 0 or self.read > 0:
            sd = np.sqrt(np.maximum(img, 0) * self.shot + self.read**2).astype(np.float32)
            img = img + sd * rng.standard_normal(img.shape, dtype=np.float32)
        # soft shoulder (extended Reinhard, white = 2) + sRGB encoding, through a 16-bit lookup table
        idx = np.clip(img * np.float32(_LUT_SCALE), 0, _LUT_SIZE - 1).astype(np.uint16)
        return _tone_lut()[idx]

"""Image metrics: PSNR, SSIM and LPIPS (AlexNet, v0.1) in plain torch.

LPIPS normally needs torchvision's AlexNet, which does not import on CPU-only torch here, so the
AlexNet feature layers are built with ``torch.nn`` and the complete LPIPS(alex, v0.1) state dict is
loaded from a file (the ``lpips`` package's key layout). Missing weights are reported as ``None``,
never as a number.

Example:
    >>> import torch
    >>> a = torch.rand(32, 32, 3); b = a.clone()
    >>> float(psnr(a, b)) > 100
    True
    >>> round(float(ssim(a, b)), 4)
    1.0
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import torch
import torch.nn.functional as F

from plantsplat.log import get_logger
from plantsplat.raster.ssim import ssim_map_cpu

log = get_logger(__name__)

# ---------------------------------------------------------------------------------------------
# PSNR / SSIM


def psnr(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB of images in [0, 1].

    Args:
        pred, gt: ``[H, W, 3]`` (or any equal shapes) in [0, 1].
        mask: optional ``[H, W, 1]`` weights; the mean squared error is taken over masked pixels only.

    Example:
        >>> import torch
        >>> round(float(psnr(torch.zeros(4, 4, 3), torch.full((4, 4, 3), 0.1))), 2)
        20.0
    """
    se = (pred - gt) ** 2
    if mask is None:
        mse = se.mean()
    else:
        m = mask.expand_as(se)
        mse = (se * m).sum() / m.sum().clamp_min(1e-8)
    return -10.0 * torch.log10(mse.clamp_min(1e-12))


def mask_interior(mask: torch.Tensor, px: int = 2) -> torch.Tensor:
    """The pixels of ``mask`` ``[H, W, 1]`` (> 0.5) whose ``(2 px + 1)``-square neighbourhood, within the image,
    lies inside it, as ``[H, W, 1]`` float: the foreground without its outline, where a frame's pixels mix the
    object with what is behind it (the image's border is no such outline).

    Example:
        >>> import torch
        >>> m = torch.zeros(9, 9, 1); m[1:8, 1:8] = 1
        >>> int(mask_interior(m, 2).sum())  # the 7 x 7 square loses a 2 px ring
        9
    """
    inside = (mask[..., 0] > 0.5).float()[None, None]  # [1, 1, H, W]
    eroded = -torch.nn.functional.max_pool2d(-inside, 2 * px + 1, stride=1, padding=px)
    return eroded[0, 0, :, :, None]


def _gaussian_window(size: int = 11, sigma: float = 1.5, dtype=torch.float32) -> torch.Tensor:
    x = torch.arange(size, dtype=dtype) - (size - 1) / 2.0
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()  # [size]


def ssim_map(pred: torch.Tensor, gt: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Per-pixel SSIM (Wang et al. 2004, 11x11 Gaussian window, sigma 1.5, as in 3DGS).

    Args:
        pred, gt: ``[H, W, C]`` in [0, 1].
    Returns:
        ``[H, W, C]`` SSIM map (zero-padded borders, as in the 3DGS training loss).
    """
    x = pred.permute(2, 0, 1)[None]  # [1, C, H, W]
    y = gt.permute(2, 0, 1)[None]
    c = x.shape[1]
    g = _gaussian_window(window, sigma, x.dtype).to(x.device)
    stack = torch.cat([x, y, x * x, y * y, x * y], dim=1)  # [1, 5C, H, W]: one blur for all five maps
    n = stack.shape[1]
    kx = g.view(1, 1, 1, -1).repeat(n, 1, 1, 1).contiguous()  # [5C, 1, 1, win]
    ky = g.view(1, 1, -1, 1).repeat(n, 1, 1, 1).contiguous()  # [5C, 1, win, 1]
    pad = window // 2
    was = torch.backends.mkldnn.enabled
    torch.backends.mkldnn.enabled = False  # oneDNN's depthwise path measured 2x slower here
    try:
        b = F.conv2d(F.pad(stack, (pad, pad, 0, 0)), kx, groups=n)
        b = F.conv2d(F.pad(b, (0, 0, pad, pad)), ky, groups=n)
    finally:
        torch.backends.mkldnn.enabled = was
    mu_x, mu_y, exx, eyy, exy = b.split(c, dim=1)
    sxx = exx - mu_x**2
    syy = eyy - mu_y**2
    sxy = exy - mu_x * mu_y
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2))
    return s[0].permute(1, 2, 0)  # [H, W, C]


def scored_ssim_map(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """:func:`ssim_map` for scoring, without a gradient: on the CPU by the numba kernel
    :func:`plantsplat.raster.ssim.ssim_map_cpu` (equal within 1e-5, tested; the PyTorch convolutions took 0.36 s
    per 960x540 view, the kernel 7 ms), elsewhere by :func:`ssim_map`. ``[H, W, C]``"""
    if pred.device.type == "cpu" and pred.shape[-1] == 3:
        return ssim_map_cpu(pred, gt)
    return ssim_map(pred, gt)


def ssim(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean SSIM of two ``[H, W, C]`` images in [0, 1]; with ``mask`` ``[H, W, 1]``, the masked mean.

    Example:
        >>> import torch
        >>> x = torch.rand(16, 16, 3)
        >>> float(ssim(x, x)) > 0.999
        True
    """
    s = ssim_map(pred, gt)
    return s.mean() if mask is None else masked_mean(s, mask)


def masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of ``values`` ``[H, W, C]`` weighted by ``mask`` ``[H, W, 1]`` (a per-pixel map such as SSIM's).

    Example:
        >>> import torch
        >>> v = torch.arange(4.0).view(2, 2, 1); m = torch.tensor([[[1.0], [0.0]], [[1.0], [0.0]]])
        >>> float(masked_mean(v, m))
        1.0
    """
    m = mask.expand_as(values)
    return (values * m).sum() / m.sum().clamp_min(1e-8)


# ---------------------------------------------------------------------------------------------
# LPIPS (AlexNet, v0.1)


class _AlexNetFeatures(torch.nn.Module):
    """AlexNet's convolutional trunk split into the five LPIPS slices (indices as torchvision's)."""

    def __init__(self):
        super().__init__()
        nn = torch.nn
        self.slice1 = nn.Sequential()
        self.slice1.add_module("0", nn.Conv2d(3, 64, 11, stride=4, padding=2))
        self.slice1.add_module("1", nn.ReLU())
        self.slice2 = nn.Sequential()
        self.slice2.add_module("2", nn.MaxPool2d(3, 2))
        self.slice2.add_module("3", nn.Conv2d(64, 192, 5, padding=2))
        self.slice2.add_module("4", nn.ReLU())
        self.slice3 = nn.Sequential()
        self.slice3.add_module("5", nn.MaxPool2d(3, 2))
        self.slice3.add_module("6", nn.Conv2d(192, 384, 3, padding=1))
        self.slice3.add_module("7", nn.ReLU())
        self.slice4 = nn.Sequential()
        self.slice4.add_module("8", nn.Conv2d(384, 256, 3, padding=1))
        self.slice4.add_module("9", nn.ReLU())
        self.slice5 = nn.Sequential()
        self.slice5.add_module("10", nn.Conv2d(256, 256, 3, padding=1))
        self.slice5.add_module("11", nn.ReLU())

    def forward(self, x):
        feats = []
        for s in (self.slice1, self.slice2, self.slice3, self.slice4, self.slice5):
            x = s(x)
            feats.append(x)
        return feats


class _Lin(torch.nn.Module):
    def __init__(self, c: int):
        super().__init__()
        self.model = torch.nn.Sequential()
        self.model.add_module("0", torch.nn.Dropout(0.0))
        self.model.add_module("1", torch.nn.Conv2d(c, 1, 1, bias=False))

    def forward(self, x):
        return self.model(x)


class LPIPS(torch.nn.Module):
    """LPIPS(alex, v0.1) built in plain torch; load weights with :meth:`from_file`.

    Inputs are ``[B, 3, H, W]`` in [-1, 1]; returns ``[B]`` distances.

    Usage:
        net = LPIPS.from_file("../shared/weights/lpips_alex_v0.1.pth")
        float(net(x, y))
    """

    def __init__(self):
        super().__init__()
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1))
        self.net = _AlexNetFeatures()
        self.lins = torch.nn.ModuleList([_Lin(c) for c in (64, 192, 384, 256, 256)])

    @classmethod
    def from_file(cls, path: str | os.PathLike) -> LPIPS:
        sd = torch.load(str(path), map_location="cpu", weights_only=True)
        net = cls()
        mapped = {}
        for k, v in sd.items():
            if k.startswith("scaling_layer."):
                mapped[k.split(".", 1)[1]] = v
            elif k.startswith("net.") or k.startswith("lins."):
                mapped[k] = v
        missing, unexpected = net.load_state_dict(mapped, strict=False)
        if missing:
            raise ValueError(f"{path}: not an LPIPS(alex) state dict (missing {missing[:3]})")
        net.eval()
        for p in net.parameters():
            p.requires_grad_(False)
        return net.to(memory_format=torch.channels_last)

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        # both images through the trunk in one batch, channels last: on the CPU the convolutions run about a quarter
        # faster that way than image by image in NCHW (960x540 frames, 2026-11-29), with the same distances
        z = torch.cat([x, y]).contiguous(memory_format=torch.channels_last)
        n = x.shape[0]
        total = 0.0
        for f, lin in zip(self.net((z - self.shift) / self.scale), self.lins):
            f = f / (f.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            total = total + lin((f[:n] - f[n:]) ** 2).mean(dim=(2, 3))  # [B, 1]
        return total[:, 0]


def default_lpips_weights() -> Path | None:
    """Where LPIPS(alex) weights are looked for, in order: env ``PLANTSPLAT_LPIPS_WEIGHTS``, the
    ``lpips`` package's bundled file, ``../shared/weights/lpips_alex_v0.1.pth`` next to the repo."""
    env = os.environ.get("PLANTSPLAT_LPIPS_WEIGHTS")
    if env:
        return Path(env)
    try:  # the lpips package ships its linear heads; a complete dump of the net is preferred
        spec = importlib.util.find_spec("lpips")
        if spec and spec.origin:
            cand = Path(spec.origin).parent / "weights" / "v0.1" / "alex_full.pth"
            if cand.is_file():
                return cand
    except Exception:  # an optional package must never break the metric
        pass
    repo = Path(__file__).resolve().parents[3]
    cand = repo.parent / "shared" / "weights" / "lpips_alex_v0.1.pth"
    return cand if cand.is_file() else None


_LPIPS_CACHE: dict[str, LPIPS] = {}


def load_lpips(path: str | os.PathLike | None = None) -> LPIPS | None:
    """Load LPIPS(alex) from ``path`` (or :func:`default_lpips_weights`); ``None`` with a warning
    when no weights are found (callers then report LPIPS as missing, never as zero)."""
    p = Path(path) if path else default_lpips_weights()
    if p is None or not p.is_file():
        log.warning("LPIPS weights not found (%s); LPIPS will be reported as null. Pass --lpips-weights "
                    "or set PLANTSPLAT_LPIPS_WEIGHTS", p if p else "no candidate")
        return None
    key = str(p.resolve())
    if key not in _LPIPS_CACHE:
        try:
            _LPIPS_CACHE[key] = LPIPS.from_file(p)
        except Exception as exc:
            log.warning("%s: could not load LPIPS weights (%s); LPIPS will be reported as null", p, exc)
            return None
    return _LPIPS_CACHE[key]


@torch.no_grad()
def lpips(net: LPIPS | None, pred: torch.Tensor, gt: torch.Tensor) -> float | None:
    """LPIPS between two ``[H, W, 3]`` images in [0, 1]; ``None`` when ``net`` is ``None``."""
    if net is None:
        return None
    x = pred.permute(2, 0, 1)[None].float() * 2 - 1  # [1, 3, H, W] in [-1, 1]
    y = gt.permute(2, 0, 1)[None].float() * 2 - 1
    return float(net(x, y)[0])


"""The numba CPU rasterizer against the pure-torch reference (values and gradients), edge cases,
bad input, and the gsplat backend (CUDA only).

Tolerances: images within 2e-5 absolute (float32, values in [0, 1]); gradients within 1e-4
relative in the 2-norm (||g_cpu - g_ref|| / ||g_ref||) for every parameter.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from plantsplat.raster import RasterInputError, rasterize, resolve_backend
from plantsplat.raster.cpu_order import depth_order

GRAD_RTOL = 1e-4
IMG_ATOL = 2e-5


def _camera(width: int, height: int, f: float | None = None):
    f = f or 0.9 * width
    K = torch.tensor([[f, 0.0, width / 2 + 0.3], [0.0, f * 1.05, height / 2 - 0.2], [0.0, 0.0, 1.0]])
    # a rotated, translated camera (not the identity) so viewmat gradients paths are exercised
    ang = 0.3
    R = torch.tensor([[math.cos(ang), 0.0, math.sin(ang)], [0.0, 1.0, 0.0], [-math.sin(ang), 0.0, math.cos(ang)]])
    t = torch.tensor([0.1, -0.05, 0.2])
    V = torch.eye(4)
    V[:3, :3] = R
    V[:3, 3] = t
    return V, K


def _scene(n: int, seed: int, edge_cases: bool = True, sh_degree: int | None = None):
    g = torch.Generator().manual_seed(seed)
    V, _ = _camera(8, 8)
    # sample in camera space, then map to world, so most Gaussians are in view
    z = torch.rand(n, generator=g) * 2.0 + 1.5
    xy = (torch.rand(n, 2, generator=g) - 0.5) * 1.3 * z[:, None]
    pc = torch.cat([xy, z[:, None]], dim=1)
    R, t = V[:3, :3], V[:3, 3]
    means = (pc - t) @ R  # world = R^T (pc - t)
    quats = torch.randn(n, 4, generator=g)
    scales = torch.exp(torch.randn(n, 3, generator=g) * 0.4) * 0.04
    opac = torch.rand(n, generator=g) * 0.85 + 0.1
    if sh_degree is None:
        colors = torch.rand(n, 3, generator=g)
    else:
        colors = torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g) * 0.3
    if edge_cases and n >= 8:
        means[0] = (torch.tensor([0.0, 0.0, -1.0]) - t) @ R  # behind the camera
        means[1] = (torch.tensor([0.0, 0.0, 0.0]) - t) @ R  # at the camera centre (z = 0)
        means[2] = (torch.tensor([1.3, 0.2, 2.0]) - t) @ R  # partly off-screen (right edge)
        scales[3] = torch.tensor([3.0, 2.5, 2.0])  # huge: covers the whole image
        opac[3] = 0.15
        scales[4] = torch.tensor([1e-6, 1e-6, 1e-6])  # degenerate: only the eps2d blur remains
        scales[5] = torch.tensor([0.2, 1e-7, 0.05])  # flat
        opac[6] = 0.002  # below 1/255: culled
        means[7] = (torch.tensor([-5.0, 0.0, 2.0]) - t) @ R  # far outside the view
    return [means, quats, scales, opac, colors]


def _run(params, width, height, backend, sh_degree=None, grad_w=None, tile_size=16):
    params = [p.detach().clone().requires_grad_(True) for p in params]
    V, K = _camera(width, height)
    out = rasterize(*params, V, K, width, height, sh_degree=sh_degree, backend=backend, tile_size=tile_size)
    if grad_w is None:
        gen = torch.Generator().manual_seed(123)
        grad_w = (torch.randn(height, width, 3, generator=gen), torch.randn(height, width, 1, generator=gen),
                  torch.randn(height, width, 1, generator=gen))
    loss = (out.color * grad_w[0]).sum() + (out.alpha * grad_w[1]).sum() + (out.depth * grad_w[2]).sum()
    loss.backward()
    grads = [p.grad for p in params]
    m2g = out.means2d.grad
    return out, grads, m2g


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    den = float(b.norm())
    return float((a - b).norm()) / den if den > 0 else float(a.norm())


def _compare(params, width, height, sh_degree=None, tile_size=16):
    ref, gref, m2ref = _run(params, width, height, "reference", sh_degree, tile_size=tile_size)
    cpu, gcpu, m2cpu = _run(params, width, height, "cpu", sh_degree, tile_size=tile_size)
    torch.testing.assert_close(cpu.color, ref.color, atol=IMG_ATOL, rtol=0)
    torch.testing.assert_close(cpu.alpha, ref.alpha, atol=IMG_ATOL, rtol=0)
    torch.testing.assert_close(cpu.depth, ref.depth, atol=IMG_ATOL * 10, rtol=1e-5)
    assert torch.equal(cpu.radii, ref.radii) and torch.equal(cpu.visible, ref.visible)
    names = ["means", "quats", "scales", "opacities", "colors"]
    for name, a, b in zip(names, gcpu, gref):
        assert torch.isfinite(a).all(), name
        assert _rel(a, b) < GRAD_RTOL, (name, _rel(a, b))
    assert _rel(m2cpu, m2ref) < GRAD_RTOL
    return ref, cpu


@pytest.mark.parametrize("seed,width,height", [(0, 37, 29), (1, 64, 48), (2, 20, 33)])
def test_cpu_matches_reference_values_and_gradients(seed, width, height):
    ref, cpu = _compare(_scene(120, seed), width, height)
    assert float(ref.alpha.detach().max()) > 0.5  # the scene is not empty
    assert not bool(cpu.visible[0]) and not bool(cpu.visible[1])  # behind / at the camera: culled
    assert not bool(cpu.visible[6]) and not bool(cpu.visible[7])  # transparent / far off-screen
    assert bool(cpu.visible[3])  # the huge one is kept


def test_cpu_matches_reference_with_sh_degree_3():
    _compare(_scene(60, 5, sh_degree=3), 40, 30, sh_degree=3)


def test_trailing_background_gaussians_are_dropped_without_changing_the_composite_or_gradients():
    """Gaussians coloured as the background (the trainer's occluders) with nothing else behind them in a
    tile: the cpu backend drops them there, the composite over that background and every gradient stay
    the reference's (which draws them all), and only alpha shows they were left out."""
    width, height, n_bg = 48, 40, 60
    bg = torch.tensor([0.2, 0.7, 0.4])
    params = _scene(120 + n_bg, 21, edge_cases=False)
    params[4][-n_bg:] = bg  # background-coloured; the _scene depths interleave them with the others
    params[2][-n_bg:] *= 2.0  # larger, so some tiles hold nothing else
    V, K = _camera(width, height)
    gen = torch.Generator().manual_seed(5)
    w = torch.randn(height, width, 3, generator=gen)

    def run(backend, trailing):
        ps = [p.detach().clone().requires_grad_(i < 4) for i, p in enumerate(params)]
        out = rasterize(*ps, V, K, width, height, backend=backend, trailing_background=trailing)
        comp = out.color + (1 - out.alpha) * bg
        (comp * w).sum().backward()
        return comp.detach(), out.alpha.detach(), [p.grad for p in ps[:4]]

    ref_c, ref_a, ref_g = run("reference", 0)
    cpu_c, cpu_a, cpu_g = run("cpu", n_bg)
    torch.testing.assert_close(cpu_c, ref_c, atol=IMG_ATOL, rtol=0)
    for name, a, b in zip(["means", "quats", "scales", "opacities"], cpu_g, ref_g):
        assert _rel(a, b) < GRAD_RTOL, (name, _rel(a, b))
    assert float((ref_a - cpu_a).max()) > 0.1  # some trailing background Gaussians were dropped
    with pytest.raises(RasterInputError, match="trailing_background"):
        rasterize(*params, V, K, width, height, backend="cpu", trailing_background=len(params[0]) + 1)


def test_cpu_matches_reference_other_tile_size():
    _compare(_scene(80, 6), 45, 27, tile_size=8)


def test_dense_opaque_scene_stops_early_like_the_reference():
    params = _scene(300, 7, edge_cases=False)
    params[3] = torch.full((300,), 0.98)  # nearly opaque: pixels reach T <= 1e-4 and stop
    params[2] = params[2] * 6
    ref, cpu = _compare(params, 24, 20)
    assert float((ref.alpha.detach() >= 1 - 1e-4 / 0.02).float().mean()) > 0.5  # most pixels stopped early


def test_reference_matches_per_pixel_definition():
    """The reference's dense compositing against a literal per-pixel loop of the definition."""
    from plantsplat.raster.projection import project_gaussians

    params = _scene(40, 8, edge_cases=False)
    W, H = 24, 18
    V, K = _camera(W, H)
    out = rasterize(*params, V, K, W, H, backend="reference")
    m2, con, z, r = project_gaussians(params[0], params[1], params[2], params[3], V, K, W, H)
    order = sorted(range(40), key=lambda i: float(z[i]))
    for (px, py) in [(3, 4), (12, 9), (20, 15)]:
        T, c = 1.0, torch.zeros(3)
        for i in order:
            if not (r[i] > 0).all():
                continue
            # tile test (16 px tiles) as gsplat
            tx0 = max(0, math.floor((float(m2[i, 0]) - int(r[i, 0])) / 16))
            tx1 = math.ceil((float(m2[i, 0]) + int(r[i, 0])) / 16)
            ty0 = max(0, math.floor((float(m2[i, 1]) - int(r[i, 1])) / 16))
            ty1 = math.ceil((float(m2[i, 1]) + int(r[i, 1])) / 16)
            if not (tx0 <= px // 16 < tx1 and ty0 <= py // 16 < ty1):
                continue
            dx, dy = float(m2[i, 0]) - (px + 0.5), float(m2[i, 1]) - (py + 0.5)
            a, b, cc = (float(v) for v in con[i])
            sig = 0.5 * (a * dx * dx + cc * dy * dy) + b * dx * dy
            al = min(0.999, float(params[3][i]) * math.exp(-sig))
            if sig < 0 or al < 1 / 255:
                continue
            if T * (1 - al) <= 1e-4:
                break
            c += params[4][i] * al * T
            T *= 1 - al
        torch.testing.assert_close(out.color[py, px], c, atol=1e-5, rtol=0)
        assert abs(float(out.alpha[py, px, 0]) - (1 - T)) < 1e-5


def test_single_pixel_and_zero_gaussians():
    _compare(_scene(30, 9), 1, 1)
    empty = [torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 3)]
    for backend in ("cpu", "reference"):
        out, grads, m2g = _run(empty, 17, 9, backend)
        assert out.color.shape == (9, 17, 3) and float(out.alpha.detach().abs().sum()) == 0.0
        assert float(out.depth.detach().abs().sum()) == 0.0 and out.radii.shape == (0,)
        assert all(g is None or g.numel() == 0 for g in grads)


def test_all_culled_gives_empty_image_and_finite_zero_gradients():
    params = _scene(20, 10, edge_cases=False)
    V, _ = _camera(8, 8)
    params[0] = (torch.tensor([0.0, 0.0, -2.0]) + 0.01 * torch.randn(20, 3) - V[:3, 3]) @ V[:3, :3]  # behind
    out, grads, _ = _run(params, 30, 20, "cpu")
    assert float(out.alpha.detach().abs().sum()) == 0.0 and not bool(out.visible.any())
    for g in grads:
        assert g is not None and torch.isfinite(g).all() and float(g.abs().sum()) == 0.0


def _depth_order_by_keys(depths: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """The reference order: numpy's sort of the 64-bit keys (depth bits, index) of the visible Gaussians."""
    vis = np.flatnonzero(counts)
    z = depths[vis]
    bits = np.where(z > 0, z, np.float32(0.0)).view(np.uint32).astype(np.uint64)
    keys = np.sort((bits << np.uint64(32)) | vis.astype(np.uint64))
    return (keys & np.uint64(0xFFFFFFFF)).astype(np.int64)


@pytest.mark.parametrize("n", [0, 1, 7, 3000, 70_000])
def test_depth_order_is_the_order_of_a_sort_by_depth_then_index(n):
    """The compositor's radix sort gives the order of a sort of (depth bits, index) keys: ties (many, at every
    digit), depths below zero, -0.0 and NaN (as 0), hidden Gaussians left out; and keys that share their top digits
    (passes skipped)."""
    rng = np.random.default_rng(n)
    depths = (rng.random(n) * 50 + 0.05).astype(np.float32)
    if n > 10:
        depths[rng.integers(0, n, n // 3)] = depths[rng.integers(0, n, n // 3)]  # repeated depths
        depths[:4] = [-1.0, -0.0, np.nan, 0.0]
    counts = rng.integers(0, 3, n)
    assert np.array_equal(depth_order(depths, counts), _depth_order_by_keys(depths, counts))
    near = (1.0 + rng.integers(0, 5, n) * 1e-6).astype(np.float32)  # one exponent, few low digits
    assert np.array_equal(depth_order(near, counts), _depth_order_by_keys(near, counts))


def test_no_grad_path_matches_training_path():
    params = _scene(150, 11)
    V, K = _camera(50, 40)
    with torch.no_grad():
        fast = rasterize(*params, V, K, 50, 40, backend="cpu")
    slow, _, _ = _run(params, 50, 40, "cpu")
    assert torch.equal(fast.color, slow.color.detach()) and torch.equal(fast.alpha, slow.alpha.detach())
    assert fast.means2d.grad is None and not fast.color.requires_grad


def _dense(n, seed):
    params = _scene(n, seed, edge_cases=False)
    params[3] = torch.full((n,), 0.98)
    params[2] = params[2] * 6
    return params


@pytest.mark.parametrize("make,width,height,tile", [
    (lambda: _scene(150, 12), 50, 40, 16),  # behind the camera, off-screen, huge, degenerate, culled
    (lambda: _dense(300, 13), 24, 20, 16),  # most pixels stop early
    (lambda: _scene(80, 14), 45, 27, 8),
    (lambda: _scene(30, 15), 1, 1, 16),  # a single pixel
    (lambda: [torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 3)], 17, 9, 16),
])
def test_no_grad_render_kernel_matches_reference(make, width, height, tile):
    """The render-only kernel (no backward bookkeeping) against the reference, edge cases included."""
    params = make()
    V, K = _camera(width, height)
    with torch.no_grad():
        fast = rasterize(*params, V, K, width, height, backend="cpu", tile_size=tile)
        ref = rasterize(*params, V, K, width, height, backend="reference", tile_size=tile)
    torch.testing.assert_close(fast.color, ref.color, atol=IMG_ATOL, rtol=0)
    torch.testing.assert_close(fast.alpha, ref.alpha, atol=IMG_ATOL, rtol=0)
    torch.testing.assert_close(fast.depth, ref.depth, atol=IMG_ATOL * 10, rtol=1e-5)
    assert torch.equal(fast.radii, ref.radii)


def _extreme(n, seed):
    """Very elongated (up to 1:2000, any rotation), large, tiny and nearly transparent Gaussians."""
    params = _scene(n, seed, edge_cases=False)
    g = torch.Generator().manual_seed(seed + 1000)
    kind = torch.randint(0, 4, (n,), generator=g)
    s = params[2]
    long = torch.exp(torch.rand(n, generator=g) * 2.0 - 2.5)  # 0.007 .. 0.6
    s[kind == 0] = torch.stack([long, long * 5e-4, long * 1e-3], 1)[kind == 0]  # needles
    s[kind == 1] = torch.stack([long, long, long * 1e-3], 1)[kind == 1]  # flat discs seen at any angle
    s[kind == 2] = s[kind == 2] * 1e-3  # tiny: only the eps2d blur
    params[3] = torch.where(kind == 3, 1 / 255 + torch.rand(n, generator=g) * 0.01, params[3])  # faint
    params[3][:5] = 1.0  # fully opaque (alpha clamped to 0.999)
    return params


@pytest.mark.parametrize("seed,width,height,tile", [(30, 64, 48, 16), (31, 53, 37, 8), (32, 96, 20, 16)])
def test_tile_culling_keeps_every_contributing_gaussian(seed, width, height, tile):
    """Extreme Gaussians (needles, discs edge-on, tiny, faint, opaque): the culled tile boxes and
    per-block row ranges lose nothing. The compositing alone (same projected 2D Gaussians) against
    the reference, which tests every pixel of every tile in gsplat's box: render-only and training
    outputs, and the gradients of all 2D parameters. (The 3D gradients of such needles differ from
    the reference's by up to 2e-4 in float32 through the projection, with or without culling.)"""
    from plantsplat.raster.cpu import composite_cpu
    from plantsplat.raster.projection import project_gaussians
    from plantsplat.raster.reference import composite_reference

    params = _extreme(200, seed)
    V, K = _camera(width, height)
    with torch.no_grad():
        m2, con, z, r = project_gaussians(params[0], params[1], params[2], params[3], V, K, width, height)
    base = [m2, con, params[4], params[3], z]
    gen = torch.Generator().manual_seed(seed)
    gw = [torch.randn(height, width, 3, generator=gen), torch.randn(height, width, 1, generator=gen),
          torch.randn(height, width, 1, generator=gen)]
    res = []
    for fn in (composite_reference, composite_cpu):
        with torch.no_grad():
            fast = fn(*base, r, width, height, tile)
        xs = [t.detach().clone().requires_grad_(True) for t in base]
        outs = fn(*xs, r, width, height, tile)
        sum((o * w).sum() for o, w in zip(outs, gw)).backward()
        res.append((fast, outs, [x.grad for x in xs]))
    (ref_ng, ref, gref), (cpu_ng, cpu, gcpu) = res
    assert float(ref[1].detach().max()) > 0.5
    for a, b, tol in zip(cpu_ng + tuple(o.detach() for o in cpu), ref_ng + tuple(o.detach() for o in ref),
                         [IMG_ATOL, IMG_ATOL, IMG_ATOL * 10] * 2):
        torch.testing.assert_close(a, b, atol=tol, rtol=0)
    for name, a, b in zip(["means2d", "conics", "colors", "opacities", "depths"], gcpu, gref):
        assert _rel(a, b) < GRAD_RTOL, (name, _rel(a, b))


def test_culling_region_holds_every_pixel_with_visible_alpha():
    """The culling rule itself, on 2D Gaussians drawn directly (elongated up to 1:3000, all angles,
    opacities from just above 1/255 to 1): every pixel with alpha >= 1/255 (sigma evaluated in float32
    as the kernels do) lies in the Gaussian's tile box, its column span and its block's row range."""
    import numpy as np

    from plantsplat.raster import cpu as C

    rng = np.random.default_rng(7)
    n, ts, W, H = 400, 16, 300, 300
    ang = rng.uniform(0, np.pi, n)
    sd = np.exp(rng.uniform(np.log(0.02), np.log(60.0), (n, 2)))
    cov = np.zeros((n, 2, 2))
    for i in range(n):
        R = np.array([[np.cos(ang[i]), -np.sin(ang[i])], [np.sin(ang[i]), np.cos(ang[i])]])
        cov[i] = R @ np.diag(sd[i] ** 2) @ R.T + 0.3 * np.eye(2)
    con = np.linalg.inv(cov)
    conics = np.stack([con[:, 0, 0], con[:, 0, 1], con[:, 1, 1]], 1).astype(np.float32)
    opac = np.concatenate([np.full(n // 4, 1.0), 1 / 255 * (1 + rng.uniform(1e-4, 0.05, n // 4)),
                           rng.uniform(0.01, 1.0, n - n // 2)]).astype(np.float32)
    means2d = rng.uniform(-20, W + 20, (n, 2)).astype(np.float32)
    ext = np.minimum(3.33, np.sqrt(2 * np.log(np.maximum(opac / (1 / 255), 1.0))))
    radii = np.ceil(ext[:, None] * np.sqrt(np.stack([cov[:, 0, 0], cov[:, 1, 1]], 1))).astype(np.int32)
    rec = np.empty((n, C._NREC), np.float32)
    C._records(means2d, conics, np.zeros((n, 3), np.float32), opac, np.ones(n, np.float32), radii, rec)
    tx, ty = (W + ts - 1) // ts, (H + ts - 1) // ts
    box = np.empty((n, 4), np.int32)
    counts = np.empty(n, np.int64)
    C._boxes(rec, radii, ts, tx, ty, box, counts)
    ys, xs = np.mgrid[0:H, 0:W]
    pxc, pyc = xs.astype(np.float32) + np.float32(0.5), ys.astype(np.float32) + np.float32(0.5)
    checked = 0
    for g in range(n):
        dx, dy = means2d[g, 0] - pxc, means2d[g, 1] - pyc
        sig = rec[g, 2] * dx * dx + rec[g, 4] * dy * dy + rec[g, 3] * dx * dy  # float32, as the kernels
        al = np.minimum(0.999, opac[g] * np.exp(-sig.astype(np.float64)))
        # the reference's own rules: alpha and sigma tests, tiles in gsplat's box from the radii
        bx0 = max(0, math.floor(means2d[g, 0] / ts - radii[g, 0] / ts))
        bx1 = min(tx, math.ceil(means2d[g, 0] / ts + radii[g, 0] / ts))
        by0 = max(0, math.floor(means2d[g, 1] / ts - radii[g, 1] / ts))
        by1 = min(ty, math.ceil(means2d[g, 1] / ts + radii[g, 1] / ts))
        inbox = (xs // ts >= bx0) & (xs // ts < bx1) & (ys // ts >= by0) & (ys // ts < by1)
        hit = (al >= 1 / 255) & (sig >= 0) & inbox
        for y, x in zip(*np.nonzero(hit)):
            checked += 1
            assert box[g, 0] <= x // ts < box[g, 2] and box[g, 1] <= y // ts < box[g, 3], (g, x, y)
            x0, y0 = (x // ts) * ts, (y // ts) * ts
            mx, my = np.float32(means2d[g, 0] - np.float32(x0)), np.float32(means2d[g, 1] - np.float32(y0))
            r0, r1 = C._span(my, rec[g, 11], ts)
            c0, c1 = C._span(mx, rec[g, 10], ts)
            assert r0 <= y - y0 < r1 and c0 <= x - x0 < c1, (g, x, y)
            b0, b1 = C._block_rows(mx, my, (x - x0) // C._LANES, rec[g, 12], rec[g, 13], rec[g, 14], rec[g, 15],
                                   r0, r1, ts)
            assert b0 <= y - y0 < b1, (g, x, y)
    assert checked > 10000


def test_expected_depth_convention():
    # one Gaussian at camera depth 2: ED equals 2 wherever alpha > 0, 0 elsewhere
    means = torch.tensor([[0.0, 0.0, 2.0]])
    K = torch.tensor([[40.0, 0.0, 16.0], [0.0, 40.0, 16.0], [0.0, 0.0, 1.0]])
    out = rasterize(means, torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), 0.05), torch.tensor([0.9]),
                    torch.ones(1, 3), torch.eye(4), K, 32, 32, backend="cpu")
    hit = out.alpha[..., 0] > 0
    assert hit.any() and (~hit).any()
    torch.testing.assert_close(out.depth[hit][:, 0], torch.full((int(hit.sum()),), 2.0))
    assert float(out.depth[~hit].abs().sum()) == 0.0


def test_resolve_backend():
    assert resolve_backend("cpu") == "cpu" and resolve_backend("reference") == "reference"
    assert resolve_backend("auto") in ("cpu", "gsplat")
    if not torch.cuda.is_available():
        assert resolve_backend("auto") == "cpu"
    with pytest.raises(RasterInputError, match="unknown rasterizer backend"):
        resolve_backend("vulkan")


def _good():
    p = _scene(10, 12, edge_cases=False)
    V, K = _camera(16, 16)
    return p, V, K


@pytest.mark.parametrize(
    "mutate,match",
    [
        (lambda p: p[0].__setitem__((2, 1), float("nan")), "means has 1 NaN/Inf"),
        (lambda p: p[2].__setitem__((0, 0), float("inf")), "scales has 1 NaN/Inf"),
        (lambda p: p[4].__setitem__((3, 2), float("nan")), "colors has 1 NaN/Inf"),
        (lambda p: p.__setitem__(1, p[1][:5]), r"quats has shape \[5, 4\], expected \[10, 4\]"),
        (lambda p: p.__setitem__(3, p[3][:, None]), r"opacities has shape \[10, 1\]"),
        (lambda p: p.__setitem__(0, p[0][:, :2]), r"means has shape \[10, 2\]"),
        (lambda p: p.__setitem__(3, p[3] + 1.5), "opacities must lie in"),
        (lambda p: p.__setitem__(2, -p[2]), "scales must be positive"),
    ],
)
def test_bad_parameters_raise_clear_errors(mutate, match):
    p, V, K = _good()
    mutate(p)
    with pytest.raises(RasterInputError, match=match):
        rasterize(*p, V, K, 16, 16, backend="cpu")


def test_bad_camera_and_sizes_raise_clear_errors():
    p, V, K = _good()
    with pytest.raises(RasterInputError, match="width must be a positive int"):
        rasterize(*p, V, K, 0, 16, backend="cpu")
    with pytest.raises(RasterInputError, match=r"viewmat has shape \[3, 4\]"):
        rasterize(*p, V[:3], K, 16, 16, backend="cpu")
    Kbad = K.clone()
    Kbad[0, 0] = float("nan")
    with pytest.raises(RasterInputError, match="K has 1 NaN/Inf"):
        rasterize(*p, V, Kbad, 16, 16, backend="cpu")
    with pytest.raises(RasterInputError, match="sh_degree=2 needs at least 9"):
        rasterize(*p[:4], torch.zeros(10, 4, 3), V, K, 16, 16, sh_degree=2, backend="cpu")
    with pytest.raises(RasterInputError, match="multiple of 8 up to 32"):
        rasterize(*p, V, K, 16, 16, backend="cpu", tile_size=12)
    with pytest.raises(RasterInputError, match="up to 32, got 40"):
        rasterize(*p, V, K, 16, 16, backend="cpu", tile_size=40)
    with pytest.raises(RasterInputError, match="near < far"):
        rasterize(*p, V, K, 16, 16, backend="cpu", near=2.0, far=1.0)


def test_cli_style_error_is_one_line_plantsplat_error():
    from plantsplat.errors import PlantsplatError

    p, V, K = _good()
    p[0][0, 0] = float("nan")
    with pytest.raises(PlantsplatError) as exc:
        rasterize(*p, V, K, 16, 16)
    assert "\n" not in str(exc.value)


@pytest.mark.cuda
def test_gsplat_backend_matches_cpu():  # pragma: no cover - needs a GPU
    pytest.importorskip("gsplat")
    params = _scene(200, 13)
    W, H = 64, 48
    cpu, gcpu, m2cpu = _run(params, W, H, "cpu")
    V, K = _camera(W, H)
    gp = [p.detach().clone().cuda().requires_grad_(True) for p in params]
    out = rasterize(*gp, V.cuda(), K.cuda(), W, H, backend="gsplat")
    gen = torch.Generator().manual_seed(123)
    gw = [torch.randn(H, W, 3, generator=gen), torch.randn(H, W, 1, generator=gen), torch.randn(H, W, 1, generator=gen)]
    loss = sum((o * w.cuda()).sum() for o, w in zip((out.color, out.alpha, out.depth), gw))
    loss.backward()
    torch.testing.assert_close(out.color.cpu(), cpu.color.detach(), atol=1e-4, rtol=0)
    torch.testing.assert_close(out.alpha.cpu(), cpu.alpha.detach(), atol=1e-4, rtol=0)
    for a, b in zip(gp, gcpu):
        assert _rel(a.grad.cpu(), b) < 1e-3
    assert _rel(out.means2d.grad.cpu(), m2cpu) < 1e-3


def test_spherical_harmonics_match_gsplat_published_formula():
    """Degree-3 SH against the constants of gsplat's CUDA ``sh_coeffs_to_color_fast`` (Sloan 2013)."""
    from plantsplat.raster.projection import spherical_harmonics

    g = torch.Generator().manual_seed(3)
    d, c = torch.randn(50, 3, generator=g), torch.randn(50, 16, 3, generator=g)
    x, y, z = (d / d.norm(dim=1, keepdim=True)).unbind(-1)
    fc1, fs1, z2 = x * x - y * y, 2 * x * y, z * z
    t0b, t0c, t1b = -1.092548430592079 * z, -2.285228997322329 * z2 + 0.4570457994644658, 1.445305721320277 * z
    fc2, fs2 = x * fc1 - y * fs1, x * fs1 + y * fc1
    basis = [
        torch.full_like(x, 0.2820947917738781), -0.48860251190292 * y, 0.48860251190292 * z, -0.48860251190292 * x,
        0.5462742152960395 * fs1, t0b * y, 0.9461746957575601 * z2 - 0.3153915652525201, t0b * x,
        0.5462742152960395 * fc1, -0.5900435899266435 * fs2, t1b * fs1, t0c * y,
        z * (1.865881662950577 * z2 - 1.119528997770346), t0c * x, t1b * fc1, -0.5900435899266435 * fc2,
    ]
    expected = sum(b[:, None] * c[:, k] for k, b in enumerate(basis))
    torch.testing.assert_close(spherical_harmonics(3, d, c), expected, atol=2e-6, rtol=0)
    torch.testing.assert_close(spherical_harmonics(1, d, c[:, :4]), sum(b[:, None] * c[:, k] for k, b in enumerate(basis[:4])),
                               atol=2e-6, rtol=0)


@pytest.mark.parametrize("h,w", [(37, 29), (64, 48), (150, 20), (5, 3), (1, 1)])
def test_fused_ssim_matches_torch_ssim_values_and_gradients(h, w):
    """The numba SSIM loss (used by the CPU training benchmark) against the PyTorch definition in
    plantsplat.train.metrics (zero-padded 11x11 Gaussian window): value within 1e-6, gradient within
    1e-4 relative; identical images give exactly the maximum."""
    from plantsplat.raster.ssim import ssim_cpu
    from plantsplat.train.metrics import ssim

    g = torch.Generator().manual_seed(h * 100 + w)
    gt = torch.rand(h, w, 3, generator=g)
    pred = (gt + 0.15 * torch.randn(h, w, 3, generator=g)).clamp(0, 1)
    a = pred.clone().requires_grad_(True)
    b = pred.clone().requires_grad_(True)
    va, vb = ssim(a, gt), ssim_cpu(b, gt)
    (va * 3.0).backward()
    (vb * 3.0).backward()
    assert abs(float(va.detach()) - float(vb.detach())) < 1e-6
    assert _rel(b.grad, a.grad) < GRAD_RTOL, _rel(b.grad, a.grad)
    with torch.no_grad():
        assert abs(float(ssim_cpu(gt, gt)) - float(ssim(gt, gt))) < 1e-6
    with pytest.raises(ValueError):
        ssim_cpu(pred, gt[:, :-1] if w > 1 else gt[:-1])


@pytest.mark.parametrize("h,w", [(540, 960), (37, 29), (150, 20), (5, 3), (1, 1)])
def test_ssim_map_kernel_matches_torch_ssim_map(h, w):
    """The numba SSIM map (the evaluation's scores) against the PyTorch definition in plantsplat.train.metrics in
    float64, borders (zero padding) and images smaller than the window included: each pixel within 3e-4 and the mean
    within 1e-6. (In float32 both lose digits where a window is nearly flat, its variance a difference of nearly
    equal moments: PyTorch's float32 map is up to 1.1e-4 off there, the kernel's 1.2e-4.)"""
    from plantsplat.raster.ssim import ssim_map_cpu
    from plantsplat.train.metrics import scored_ssim_map, ssim_map

    g = torch.Generator().manual_seed(h * 1000 + w)
    gt = torch.rand(h, w, 3, generator=g)
    pred = (gt + 0.15 * torch.randn(h, w, 3, generator=g)).clamp(0, 1)
    pred[: h // 2, : w // 2] = gt[: h // 2, : w // 2] = 0.5  # a flat corner, equal in both
    ref, fast = ssim_map(pred.double(), gt.double()), ssim_map_cpu(pred, gt)
    assert fast.shape == ref.shape and fast.dtype == torch.float32
    assert float((fast - ref).abs().max()) < 3e-4 and abs(float(fast.double().mean() - ref.mean())) < 1e-6
    assert torch.equal(scored_ssim_map(pred, gt), fast)
    with pytest.raises(ValueError):
        ssim_map_cpu(pred, gt[:, :-1] if w > 1 else gt[:-1])


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_numba_sh_colours_match_torch_values_and_gradients(degree):
    """sh_colors_cpu (the cpu backend's SH colours) against the autograd version the reference backend
    uses, clamp max(SH + 0.5, 0) included: values within 2e-6, gradients of means and coefficients within
    1e-5 relative; with more coefficients than the degree needs (extra ones: zero gradient), clamped
    colours, a Gaussian at the camera centre, and float64 input."""
    from plantsplat.raster.projection import spherical_harmonics
    from plantsplat.raster.sh_cpu import sh_colors_cpu

    g = torch.Generator().manual_seed(10 + degree)
    n = 300
    campos = torch.tensor([0.4, -0.3, 1.2])
    means = campos + torch.randn(n, 3, generator=g) * 2.0
    means[0] = campos  # zero direction: F.normalize gives 0
    means[1] = campos + torch.tensor([1e-3, 0.0, 0.0])  # very short direction
    coeffs = torch.randn(n, 16, 3, generator=g) * 0.6  # K = 16 > (degree + 1)^2 except at degree 3
    gw = torch.randn(n, 3, generator=g)
    for dtype in (torch.float32, torch.float64):
        res = []
        for fn in ("torch", "numba"):
            m = means.detach().clone().to(dtype).requires_grad_(True)
            c = coeffs.detach().clone().to(dtype).requires_grad_(True)
            if fn == "torch":
                rgb = torch.clamp_min(spherical_harmonics(degree, m - campos.to(dtype), c) + 0.5, 0.0)
            else:
                rgb = sh_colors_cpu(degree, m, campos.to(dtype), c)
            (rgb * gw.to(dtype)).sum().backward()
            res.append((rgb.detach(), m.grad, c.grad))
        (r_ref, gm_ref, gc_ref), (r, gm, gc) = res
        assert r.dtype == dtype and 0 < int((r_ref == 0).sum()) < r.numel()  # some colours are clamped
        torch.testing.assert_close(r, r_ref, atol=2e-6, rtol=0)
        assert _rel(gc, gc_ref) < 1e-5
        nb = (degree + 1) ** 2
        assert float(gc[:, nb:].abs().sum()) == 0.0 and float(gc[:, :nb].abs().sum()) > 0
        if degree == 0:
            assert gm_ref is None and gm is None  # the colour does not depend on the direction
        else:
            # row 0 (at the camera centre: gradient / 1e-12, as F.normalize) apart, or it hides the others
            assert _rel(gm[:1], gm_ref[:1]) < 1e-5, _rel(gm[:1], gm_ref[:1])
            assert _rel(gm[1:], gm_ref[1:]) < 1e-5, _rel(gm[1:], gm_ref[1:])
            assert float(gm[1:].abs().sum()) > 0
    with pytest.raises(ValueError):
        sh_colors_cpu(2, means, campos, coeffs[:, :4])
    with pytest.raises(ValueError):
        sh_colors_cpu(4, means, campos, coeffs)


def _differences(a, b) -> list[str]:
    """The arrays of two kernel_outputs.py files that differ, each with its largest difference and count."""
    out = []
    for name in a.files:
        if not np.array_equal(a[name], b[name]):
            d = np.abs(a[name].astype(np.float64) - b[name])
            out.append(f"{name} (max {d.max():.3g}, {int((d > 0).sum())} of {d.size})")
    return out


@pytest.mark.slow
def test_freshly_compiled_kernels_match_cached_ones_bit_for_bit(tmp_path):
    """The first run after an install compiles the numba kernels; later runs load them from numba's cache. Both
    must give the same images and gradients to the last bit, or the same capture gives other results on its
    first run (see plantsplat.raster.numba_config). A second cached run tells, when they differ, whether the
    compiled code or a run-to-run difference is the cause."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba_cache")}
    script = Path(__file__).with_name("kernel_outputs.py")
    runs = ("compiled", "cached", "cached_again")
    for run in runs:
        subprocess.run([sys.executable, str(script), str(tmp_path / f"{run}.npz")], env=env, check=True, timeout=900)
    compiled, cached, again = (np.load(tmp_path / f"{run}.npz") for run in runs)
    assert any((tmp_path / "numba_cache").rglob("*.nbc")), "the first process wrote no kernel cache"
    assert sorted(compiled.files) == sorted(cached.files) == sorted(again.files)
    assert not _differences(cached, again), f"two cached runs differ: {_differences(cached, again)}"
    assert not _differences(compiled, cached), f"compiled and cached kernels differ: {_differences(compiled, cached)}"

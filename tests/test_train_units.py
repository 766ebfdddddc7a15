"""Unit tests of the trainer's parts against independent references: metrics (OpenCV SSIM, the
LPIPS test vector), Inria PLY round trip, density control, the split, camera loading."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from plantsplat.errors import PlantsplatError

WEIGHTS = Path(__file__).resolve().parents[2] / "shared" / "weights"


def _ssim_opencv(a: np.ndarray, b: np.ndarray) -> float:
    """SSIM of the OpenCV tutorial (GaussianBlur 11x11, sigma 1.5), zero-padded borders as ours."""
    import cv2

    a, b = a.astype(np.float64), b.astype(np.float64)
    blur = lambda x: cv2.GaussianBlur(x, (11, 11), 1.5, borderType=cv2.BORDER_CONSTANT)  # noqa: E731
    mu_a, mu_b = blur(a), blur(b)
    saa, sbb, sab = blur(a * a) - mu_a**2, blur(b * b) - mu_b**2, blur(a * b) - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    m = ((2 * mu_a * mu_b + c1) * (2 * sab + c2)) / ((mu_a**2 + mu_b**2 + c1) * (saa + sbb + c2))
    return float(m.mean())


def test_psnr_ssim_against_references():
    from plantsplat.train.metrics import psnr, ssim

    rng = np.random.default_rng(0)
    a = rng.random((40, 50, 3)).astype(np.float32)
    b = np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1).astype(np.float32)
    mse = float(((a - b) ** 2).mean())
    assert float(psnr(torch.from_numpy(a), torch.from_numpy(b))) == pytest.approx(-10 * np.log10(mse), rel=1e-5)
    assert float(ssim(torch.from_numpy(a), torch.from_numpy(b))) == pytest.approx(_ssim_opencv(a, b), abs=1e-4)
    # masked: only the masked pixels count
    m = np.zeros((40, 50, 1), np.float32)
    m[:20] = 1
    mse_top = float(((a[:20] - b[:20]) ** 2).mean())
    assert float(psnr(torch.from_numpy(a), torch.from_numpy(b), torch.from_numpy(m))) == pytest.approx(
        -10 * np.log10(mse_top), rel=1e-5)


def test_mask_interior_is_an_erosion():
    """The evaluation's mask interior equals OpenCV's erosion by a (2 px + 1) square (the image's border is no
    outline: the frame's edge does not mix the object with the room)."""
    import cv2

    from plantsplat.train.metrics import mask_interior

    rng = np.random.default_rng(1)
    m = (cv2.GaussianBlur(rng.random((60, 70)), (0, 0), 3) > 0.5).astype(np.uint8)
    m[:, :5] = 1  # a run along the border
    for px in (1, 2):
        ref = cv2.erode(m, np.ones((2 * px + 1, 2 * px + 1), np.uint8))
        got = mask_interior(torch.from_numpy(m).float()[..., None], px)[..., 0].numpy()
        assert 0 < ref.sum() < m.sum() and np.array_equal(got.astype(np.uint8), ref)


def test_ssim_gradient_flows():
    from plantsplat.train.metrics import ssim

    x = torch.rand(24, 24, 3, requires_grad=True)
    y = torch.rand(24, 24, 3)
    (1 - ssim(x, y)).backward()
    assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


def test_fused_ssim_moment_gradients_where_the_covariance_cancels_c2():
    """The fused kernel's derivatives of SSIM by its local moments stay finite, and equal float64 central
    differences, also where 2 cov(x, y) + C2 is exactly zero (the SSIM value is then 0). Written with
    1 / (2 cov + C2) they were 0 * inf = NaN there while the loss was finite: NaN reached every Gaussian
    drawn near that pixel."""
    from plantsplat.raster.ssim import _C1, _C2, _ssim_row_grad

    # columns: moments mu_x, mu_y, E[x^2], E[y^2], E[x y]; the first has 2 (E[xy] - mu_x mu_y) + C2 == 0 exactly
    mu = np.array([[0.0, 0.3, 0.7], [0.0, 0.5, 0.2], [0.01, 0.12, 0.52], [0.02, 0.3, 0.06], [-_C2 / 2, 0.14, 0.13]],
                  np.float32)
    d = np.zeros((3, 3), np.float32)
    _ssim_row_grad(mu[0], mu[1], mu[2], mu[3], mu[4], d[0], d[1], d[2])
    assert np.isfinite(d).all()

    def ssim64(m):
        mx, my, xx, yy, xy = m
        return (2 * mx * my + _C1) * (2 * (xy - mx * my) + _C2) / ((mx**2 + my**2 + _C1) * (xx + yy - mx**2 - my**2 + _C2))

    m64 = mu.astype(np.float64)
    for row, k in ((0, 0), (1, 2), (2, 4)):  # d0: by mu_x, d1: by E[x^2], d2: by E[x y]
        e = np.zeros_like(m64)
        e[k] = 1e-6
        num = (ssim64(m64 + e) - ssim64(m64 - e)) / 2e-6
        np.testing.assert_allclose(d[row], num, rtol=2e-3, atol=2e-3)


@pytest.mark.parametrize("h,w,lam", [(83, 61, 0.2), (12, 200, 0.2), (1, 1, 0.5), (40, 7, 1.0)])
def test_training_loss_is_fused_and_matches_torch(h, w, lam):
    """The training loss (loss.photometric_loss: the fused numba kernels on the CPU) gives the same
    value, MSE and gradients of colour and alpha as the PyTorch composition: render composited over a
    background, (1 - l) L1 + l (1 - SSIM) with train.metrics.ssim. Values within 1e-6, gradients within
    1e-4 of the largest."""
    from plantsplat.train import loss as trainer_loss
    from plantsplat.train.metrics import ssim as ssim_torch

    g = torch.Generator().manual_seed(h * w)
    bg = torch.rand(3, generator=g)
    a = torch.rand(h, w, 1, generator=g)
    gt = torch.rand(h, w, 3, generator=g) * a + (1 - a) * bg
    color = (gt + 0.1 * torch.randn(h, w, 3, generator=g)).clamp(0, 1)
    color[: h // 2, : w // 3] = gt[: h // 2, : w // 3]  # exact matches: L1's subgradient is 0 there
    alpha = torch.rand(h, w, 1, generator=g)
    alpha[: h // 2, : w // 3] = 1.0

    def torch_loss(c, al):
        pred = c + (1 - al) * bg
        return (1 - lam) * (pred - gt).abs().mean() + lam * (1 - ssim_torch(pred, gt)), ((pred - gt) ** 2).mean()

    results = []
    for fn in (trainer_loss.photometric_loss, None):
        c = color.clone().requires_grad_(True)
        al = alpha.clone().requires_grad_(True)
        loss, mse = fn(c, al, bg, gt, lam) if fn else torch_loss(c, al)
        if fn:
            assert "LossCPU" in type(loss.grad_fn).__name__ or any(
                "LossCPU" in type(f).__name__ for f, _ in loss.grad_fn.next_functions if f is not None), loss.grad_fn
        (2.5 * loss).backward()
        results.append((float(loss.detach()), float(mse.detach()), c.grad, al.grad))
    (lf, mf, cf, af), (lr, mr, cr, ar) = results
    assert abs(lf - lr) < 1e-6 and abs(mf - mr) < 1e-6
    for fused, ref in ((cf, cr), (af, ar)):
        assert float((fused - ref).abs().max()) <= 1e-4 * float(ref.abs().max())
    # a ground truth that needs a gradient falls back to the PyTorch version (the fused one gives none)
    gt_req = gt.clone().requires_grad_(True)
    trainer_loss.photometric_loss(color, alpha, bg, gt_req, lam)[0].backward()
    assert gt_req.grad is not None and float(gt_req.grad.abs().sum()) > 0


@pytest.mark.parametrize("h,w", [(37, 29), (1, 5)])
def test_fused_loss_composites_a_cropped_target_like_torch(h, w):
    """Object mode passes the frame and its mask as crops (views into whole frames) with ``gt_alpha``: the fused
    loss composites the target over the background itself, and gives the value, MSE and gradients of compositing
    with PyTorch first and calling the loss on the result."""
    from plantsplat.train import loss as trainer_loss

    g = torch.Generator().manual_seed(7 * h + w)
    frame = torch.rand(h + 9, w + 11, 3, generator=g)
    mask = (torch.rand(h + 9, w + 11, 1, generator=g) > 0.4).float()
    img, ga = frame[4:4 + h, 6:6 + w], mask[4:4 + h, 6:6 + w]  # views with strided rows
    assert h == 1 or not img.is_contiguous()  # (one row of a crop counts as contiguous)
    bg = torch.rand(3, generator=g)
    color = torch.rand(h, w, 3, generator=g)
    alpha = torch.rand(h, w, 1, generator=g)
    results = []
    for crop in (True, False):
        c = color.clone().requires_grad_(True)
        al = alpha.clone().requires_grad_(True)
        if crop:
            loss, mse = trainer_loss.photometric_loss(c, al, bg, img, 0.2, ga)
        else:
            loss, mse = trainer_loss.photometric_loss(c, al, bg, (img * ga + (1 - ga) * bg).contiguous(), 0.2)
        loss.backward()
        results.append((float(loss.detach()), float(mse.detach()), c.grad, al.grad))
    (l1, m1, c1, a1), (l2, m2, c2, a2) = results
    assert abs(l1 - l2) < 1e-6 and abs(m1 - m2) < 1e-6
    assert torch.allclose(c1, c2, atol=1e-7) and torch.allclose(a1, a2, atol=1e-7)
    # the PyTorch fallback (a target that needs a gradient) composites the same way
    img_req = img.clone().requires_grad_(True)
    loss_t, _ = trainer_loss.photometric_loss(color, alpha, bg, img_req, 0.2, ga)
    assert abs(float(loss_t.detach()) - l1) < 1e-5


@pytest.mark.parametrize("case", ["corner", "two_islands", "edge_columns", "empty", "one_pixel"])
def test_fused_loss_skips_windows_where_render_and_target_agree(case):
    """Object mode's crops are mostly background over background: render and target both exactly the background
    colour. The fused loss skips the SSIM windows where they agree everywhere (SSIM exactly 1, no gradient); value
    and gradients must still equal the PyTorch composition's, with the object in a corner, as two islands, on the
    crop's left and right edges, absent, or one pixel wide."""
    import cv2

    from plantsplat.raster import ssim as S
    from plantsplat.train import loss as trainer_loss
    from plantsplat.train.metrics import ssim as ssim_torch

    h, w = 70, 90
    g = torch.Generator().manual_seed(len(case))
    obj = torch.zeros(h, w, dtype=torch.bool)
    if case == "corner":
        obj[:9, :12] = True
    elif case == "two_islands":
        obj[20:30, 10:25] = True
        obj[45:60, 60:80] = True
    elif case == "edge_columns":
        obj[30:40, :3] = True
        obj[5:15, -2:] = True
    elif case == "one_pixel":
        obj[35, 44] = True
    bg = torch.rand(3, generator=g)
    ga = (obj[..., None] & (torch.rand(h, w, 1, generator=g) > 0.2)).float()  # the target's mask
    frame = torch.rand(h, w, 3, generator=g)
    near = torch.nn.functional.max_pool2d(obj[None, None].float(), 7, 1, 3)[0, 0, ..., None] > 0  # render spills over
    alpha = torch.rand(h, w, 1, generator=g) * near
    color = torch.rand(h, w, 3, generator=g) * alpha
    target = frame * ga + (1 - ga) * bg

    def torch_loss(c, al):  # in float64: the reference's own rounding is then far below the tolerance
        pred = c + (1 - al) * bg.double()
        t = target.double()
        return 0.8 * (pred - t).abs().mean() + 0.2 * (1 - ssim_torch(pred, t)), ((pred - t) ** 2).mean()

    out = []
    for fused in (True, False):
        c = (color if fused else color.double()).clone().requires_grad_(True)
        al = (alpha if fused else alpha.double()).clone().requires_grad_(True)
        loss, mse = trainer_loss.photometric_loss(c, al, bg, frame, 0.2, ga) if fused else torch_loss(c, al)
        (3.0 * loss).backward()
        out.append((float(loss.detach()), float(mse.detach()), c.grad.double(), al.grad.double()))
    (lf, mf, cf, af), (lr, mr, cr, ar) = out
    assert abs(lf - lr) < 1e-6 and abs(mf - mr) < 1e-6
    x, y, (_, rng), _ = S._run_fwd(color, alpha[..., 0].numpy().copy(), bg.numpy(), frame, True, ga)
    differs = (x.reshape(h, w, 3) != y.reshape(h, w, 3)).any(axis=2).astype(np.uint8)
    box = np.ones((11, 11), np.uint8)
    windows = cv2.dilate(differs, box, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
    covered = torch.from_numpy(cv2.dilate(windows.astype(np.uint8), box, borderType=cv2.BORDER_CONSTANT,
                                          borderValue=0) > 0)[..., None]  # pixels some computed window holds
    for a, b in ((cf, cr), (af, ar)):
        assert float((a - b).abs().max()) <= 1e-4 * float(b.abs().max()) + 1e-10, float((a - b).abs().max())
        # no gradient the skipped windows would have given is lost: outside the computed windows the float64
        # reference's gradient is zero too (up to its rounding). Inside them a float32 sum may cancel to exactly
        # zero where the reference keeps ~1e-10: that is rounding, within the tolerance above.
        assert not bool((b[(a == 0) & ~covered.expand_as(a)].abs() >= 1e-13).any())
    # the windows computed are exactly those holding a pixel where render and target differ (a range one pixel
    # short would leave ~1e-9 of gradient out at its edge)
    for i in range(h):
        cols = np.flatnonzero(windows[i])
        assert tuple(rng[i]) == ((cols[0], cols[-1] + 1) if len(cols) else (0, 0)), (i, rng[i])
    # the backward pass reads no derivative map the forward pass left unwritten: with the maps' memory full of NaN
    # beforehand, the gradient stays finite
    n = 3 * w
    maps = np.full((3, h, n), np.nan, np.float32)
    xs, ys = np.empty((h, n), np.float32), np.empty((h, n), np.float32)
    live, rng2 = np.empty((h, 2), np.int64), np.empty((h, 2), np.int64)
    g6 = S._window()[: S._R + 1].copy()
    S._fwd(color.numpy().reshape(h, n), alpha[..., 0].numpy().copy(), bg.numpy(), ys, g6, True, xs, maps,
           np.zeros((h, 3), np.float32), frame.numpy().reshape(h, n), ga.numpy().reshape(h, w), live, rng2)
    dx = np.empty((h, n), np.float32)
    S._bwd(maps, xs, ys, bg.numpy(), g6, np.float32(1.0), np.float32(0.0), dx, np.empty((0, 0), np.float32), rng2)
    assert np.isfinite(dx).all() and (rng2 == rng).all()
    computed = int((rng[:, 1] - rng[:, 0]).sum())
    if case == "empty":
        assert computed == 0 and lf == 0.0 and float(cf.abs().max()) == 0.0
    else:
        assert 0 < computed < 0.6 * h * w


def test_fused_loss_rejects_bad_shapes():
    from plantsplat.raster.ssim import photometric_loss_cpu

    c, gt = torch.rand(8, 9, 3), torch.rand(8, 9, 3)
    for args in ((c, torch.ones(8, 9), torch.zeros(3), gt), (c, torch.ones(8, 9, 1), torch.zeros(4), gt),
                 (c, torch.ones(8, 9, 1), torch.zeros(3), gt[:, :-1]), (c[..., :2], torch.ones(8, 9, 1), torch.zeros(3),
                                                                         gt[..., :2])):
        with pytest.raises(ValueError):
            photometric_loss_cpu(*args)


@pytest.mark.skipif(not (WEIGHTS / "lpips_alex_v0.1.pth").is_file(), reason="LPIPS weights not in ../shared/weights")
def test_lpips_test_vector():
    from plantsplat.io import read_image
    from plantsplat.train.metrics import load_lpips, lpips

    net = load_lpips(WEIGHTS / "lpips_alex_v0.1.pth")
    img = lambda n: torch.from_numpy(read_image(WEIGHTS / "lpips-test" / n)).float() / 255  # noqa: E731
    ref = img("ex_ref.png")
    assert lpips(net, img("ex_p0.png"), ref) == pytest.approx(0.722, abs=1e-3)
    assert lpips(net, img("ex_p1.png"), ref) == pytest.approx(0.138, abs=1e-3)
    assert lpips(net, ref, ref) == pytest.approx(0.0, abs=1e-6)


def test_lpips_one_batch_channels_last_matches_image_by_image():
    """LPIPS runs both images through AlexNet in one channels-last batch; the distances are those of each image run on
    its own in NCHW with NCHW weights (seeded random weights, odd sizes, two pairs at once)."""
    import copy

    from plantsplat.train.metrics import LPIPS

    torch.manual_seed(0)
    net = LPIPS().eval().to(memory_format=torch.channels_last)
    with torch.no_grad():
        for lin in net.lins:  # LPIPS's linear heads weigh each channel's difference by a non-negative weight
            lin.model[1].weight.abs_()
    ref = copy.deepcopy(net).to(memory_format=torch.contiguous_format)
    x, y = torch.rand(2, 3, 67, 93) * 2 - 1, torch.rand(2, 3, 67, 93) * 2 - 1

    def by_image(a, b):
        fa, fb = (ref.net(((t - ref.shift) / ref.scale).contiguous()) for t in (a, b))
        unit = lambda f: f / (f.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)  # noqa: E731
        return sum(lin((unit(p) - unit(q)) ** 2).mean(dim=(2, 3)) for p, q, lin in zip(fa, fb, ref.lins))[:, 0]

    with torch.no_grad():
        got, want = net(x, y), torch.stack([by_image(x[i:i + 1], y[i:i + 1])[0] for i in range(2)])
    assert got.shape == (2,) and torch.allclose(got, want, rtol=1e-5, atol=1e-7)
    assert float(want.min()) > 0


def test_lpips_missing_weights_is_null(tmp_path, monkeypatch):
    from plantsplat.train.metrics import load_lpips, lpips

    monkeypatch.setenv("PLANTSPLAT_LPIPS_WEIGHTS", str(tmp_path / "none.pth"))
    net = load_lpips()
    assert net is None and lpips(net, torch.zeros(8, 8, 3), torch.ones(8, 8, 3)) is None


def _random_params(n=50, deg=2, seed=0):
    from plantsplat.train.model import init_params

    rng = np.random.default_rng(seed)
    p = init_params(rng.random((n, 3)) * 10, rng.random((n, 3)), sh_degree=deg, seed=seed)
    with torch.no_grad():
        p["shN"].normal_()
        p["opacities"].normal_()
    return p


def test_splat_ply_round_trip_and_layout(tmp_path):
    from plyfile import PlyData

    from plantsplat.ply import read_splat as read_splat_ply
    from plantsplat.ply import write_splat as write_splat_ply

    p = {k: v.detach().numpy() for k, v in _random_params(deg=3).items()}
    q = p["quats"] / np.linalg.norm(p["quats"], axis=1, keepdims=True)
    write_splat_ply(tmp_path / "s.ply", p["means"], p["scales"], q, p["opacities"], p["sh0"], p["shN"])
    names = PlyData.read(str(tmp_path / "s.ply"))["vertex"].data.dtype.names
    assert names[:9] == ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2")
    assert names[-8:] == ("opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")
    assert sum(n.startswith("f_rest_") for n in names) == 45
    g = read_splat_ply(tmp_path / "s.ply")
    for k in ("means", "scales", "opacities", "sh0", "shN"):
        np.testing.assert_allclose(g[k], p[k], rtol=1e-6)
    # Inria's channel-major f_rest: f_rest_0..14 are the red channel's 15 coefficients
    v = PlyData.read(str(tmp_path / "s.ply"))["vertex"]
    np.testing.assert_allclose(v["f_rest_1"], p["shN"][:, 1, 0], rtol=1e-6)
    np.testing.assert_allclose(v["f_rest_15"], p["shN"][:, 0, 1], rtol=1e-6)


def test_read_splat_ply_rejects_other_ply(tmp_path):
    from plantsplat.ply import read_splat as read_splat_ply
    from plantsplat.ply import write_point_cloud

    write_point_cloud(tmp_path / "p.ply", np.zeros((3, 3)), np.zeros((3, 3), np.uint8), opacity=np.ones(3),
                      scale=np.ones((3, 3)))
    with pytest.raises(PlantsplatError, match="not a 3D Gaussian Splatting PLY"):
        read_splat_ply(tmp_path / "p.ply")


def test_strategy_grow_prune_keeps_optimizer_in_sync():
    from plantsplat.train.model import make_optimizers
    from plantsplat.train.strategy import DensityStrategy

    params = _random_params(n=40)
    lrs = dict(means=1e-3, scales=1e-3, quats=1e-3, opacities=1e-2, sh0=1e-3, shN=1e-3)
    opts = make_optimizers(params, lrs)
    sum(p.sum() for p in params.values()).backward()
    for o in opts.values():
        o.step()
    with torch.no_grad():
        params["opacities"][:10] = -5.0  # opacity 0.007: pruned
        params["opacities"][10:] = 2.0
        params["scales"][:] = np.log(0.01)
        params["scales"][30:] = np.log(5.0)  # large: split instead of clone
    st = DensityStrategy(refine_start_iter=0, refine_every=1, reset_every=0, grow_grad2d=0.5)
    state = st.initialize_state(scene_scale=10.0)
    state["grad2d"] = torch.zeros(40)
    state["count"] = torch.ones(40)
    state["grad2d"][[20, 21, 35]] = 1.0  # two small (clone) and one large (split)
    st._grow(params, opts, state)
    assert params["means"].shape[0] == 40 + 2 + 1  # split replaces one by two
    st._prune(params, opts, state, step=1)
    assert params["means"].shape[0] == 33
    for name, o in opts.items():
        p = params[name]
        assert o.param_groups[0]["params"][0] is p
        assert o.state[p]["exp_avg"].shape == p.shape
    assert (torch.sigmoid(params["opacities"]) >= 0.1).all()
    # split children are 1.6x smaller than the parent
    np.testing.assert_allclose(torch.exp(params["scales"][-2:]).detach().numpy(), 5.0 / 1.6, rtol=1e-5)
    assert int((torch.exp(params["scales"][:-2]).detach().max(dim=-1).values < 4.0).sum()) == 33 - 2 - 9  # 9 large stay
    # the (fused) Adam keeps stepping on the resized moments, as the per-tensor Adam does
    assert all(o.param_groups[0]["fused"] for o in opts.values())
    ref = {k: torch.nn.Parameter(v.detach().clone()) for k, v in params.items()}
    ref_opts = {}
    for k, o in opts.items():
        ref_opts[k] = torch.optim.Adam([ref[k]], lr=lrs[k], eps=1e-15, foreach=False)
        ref_opts[k].state[ref[k]] = {n: v.clone() for n, v in o.state[params[k]].items()}
    for ps, os_ in ((params, opts), (ref, ref_opts)):
        sum((p * torch.linspace(-1, 1, p.numel()).view_as(p)).sum() for p in ps.values()).backward()
        for o in os_.values():
            o.step()
    for k in params:
        torch.testing.assert_close(params[k].detach(), ref[k].detach(), atol=1e-6, rtol=1e-5)


def test_nonfinite_gradients_are_zeroed_per_gaussian():
    """Only the Gaussians (model or occluder) with a NaN/inf entry in any gradient lose their gradients, all of
    them; the screen-space means' gradient rows follow the render's order (model first, occluders after)."""
    from plantsplat.train.loss import drop_nonfinite_grads

    def group(n, seed):
        g = torch.Generator().manual_seed(seed)
        p = torch.nn.ParameterDict({"means": torch.nn.Parameter(torch.zeros(n, 3)),
                                    "sh0": torch.nn.Parameter(torch.zeros(n, 1, 3))})
        for t in p.values():
            t.grad = torch.randn(t.shape, generator=g)
        return p

    model, occ = group(6, 0), group(4, 1)
    means2d = torch.zeros(10, 2, requires_grad=True)
    means2d.grad = torch.randn(10, 2)
    model["sh0"].grad[1, 0, 2] = float("nan")
    model["means"].grad[4, 0] = float("inf")
    means2d.grad[7, 1] = float("-inf")  # occluder 1
    before = {k: v.grad.clone() for k, v in model.items()}
    n, where = drop_nonfinite_grads([("", model), ("occluder ", occ)], means2d)
    assert n == 3 and set(where) == {"sh0", "means", "occluder means2d"}
    for k, v in model.items():
        assert torch.equal(v.grad[[1, 4]], torch.zeros_like(v.grad[[1, 4]]))
        assert torch.equal(v.grad[[0, 2, 3, 5]], before[k][[0, 2, 3, 5]])
    assert torch.equal(occ["means"].grad[1], torch.zeros(3)) and bool(occ["means"].grad[0].ne(0).all())
    assert torch.equal(means2d.grad[[1, 4, 7]], torch.zeros(3, 2)) and bool(torch.isfinite(means2d.grad).all())
    assert drop_nonfinite_grads([("", model), ("occluder ", None)], means2d) == (0, [])


def test_strategy_opacity_reset():
    from plantsplat.train.model import make_optimizers
    from plantsplat.train.strategy import DensityStrategy

    params = _random_params(n=10)
    with torch.no_grad():
        params["opacities"][:] = 3.0
    opts = make_optimizers(params, dict(means=1, scales=1, quats=1, opacities=1, sh0=1, shN=1))
    DensityStrategy(prune_opa=0.1)._reset_opacity(params, opts)
    assert torch.allclose(torch.sigmoid(params["opacities"]), torch.tensor(0.2), atol=1e-6)


def test_split_fractions():
    from plantsplat.train.data import make_split

    names = [f"frame_{i:05d}.png" for i in range(120)]
    s = make_split(names, 0.4)
    assert len(s["train"]) == 72 and len(s["test"]) == 48 and not set(s["train"]) & set(s["test"])
    s = make_split(names, test_every=8)
    assert s["test"] == names[::8]
    with pytest.raises(PlantsplatError):
        make_split(names[:3], test_every=1)


def test_transforms_and_colmap_agree(tmp_path):
    """A camera written as nerfstudio transforms.json and as a COLMAP model loads to the same pose."""
    import pycolmap

    from plantsplat.io import write_image_atomic, write_json_atomic
    from plantsplat.train.data import load_scene
    from plantsplat.workspace import Workspace

    rng = np.random.default_rng(1)
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    R *= np.sign(np.linalg.det(R))
    t = rng.normal(size=3)
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, t
    ws1, ws2 = Workspace(tmp_path / "a"), Workspace(tmp_path / "b")
    for ws in (ws1, ws2):
        for i in range(2):
            write_image_atomic(ws.images_dir / f"frame_{i:05d}.png", np.zeros((30, 40, 3), np.uint8))
    c2w_gl = np.linalg.inv(w2c) @ np.diag([1.0, -1, -1, 1])
    write_json_atomic(ws1.transforms_json, {"fl_x": 50.0, "fl_y": 50.0, "cx": 20.0, "cy": 15.0, "w": 40, "h": 30,
                                            "frames": [{"file_path": f"images/frame_{i:05d}.png",
                                                        "transform_matrix": c2w_gl.tolist()} for i in range(2)]})
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model="PINHOLE", width=40, height=30, params=[50.0, 50.0, 20.0, 15.0], camera_id=1)
    rec.add_camera_with_trivial_rig(cam) if hasattr(rec, "add_camera_with_trivial_rig") else rec.add_camera(cam)
    for i in range(2):
        im = pycolmap.Image(name=f"frame_{i:05d}.png", camera_id=1, image_id=i + 1)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(R), t)
        if hasattr(rec, "add_image_with_trivial_frame"):
            rec.add_image_with_trivial_frame(im, pose)
        else:
            im.cam_from_world = pose
            rec.add_image(im)
    ws2.sparse_dir.mkdir(parents=True)
    rec.write_binary(str(ws2.sparse_dir))
    s1, s2 = load_scene(ws1, need_masks=False), load_scene(ws2, need_masks=False)
    np.testing.assert_allclose(s1.views[0].viewmat, w2c, atol=1e-9)
    np.testing.assert_allclose(s2.views[0].viewmat, w2c, atol=1e-6)
    np.testing.assert_allclose(s1.views[0].K, s2.views[0].K)


def test_undistortion_applied(tmp_path):
    from plantsplat.io import write_image_atomic, write_json_atomic
    from plantsplat.segment.frame import distortion_map, to_frame
    from plantsplat.train.data import load_scene
    from plantsplat.workspace import Workspace

    ws = Workspace(tmp_path)
    xs = np.arange(80)[None, :, None]
    img = np.broadcast_to(127.5 + 120 * np.sin(2 * np.pi * xs / 16), (60, 80, 3)).round().astype(np.uint8)
    for i in range(2):
        write_image_atomic(ws.images_dir / f"frame_{i:05d}.png", img)
    fr = [{"file_path": f"images/frame_{i:05d}.png", "transform_matrix": np.eye(4).tolist()} for i in range(2)]
    write_json_atomic(ws.transforms_json, {"fl_x": 60.0, "fl_y": 60.0, "cx": 40.0, "cy": 30.0, "w": 80, "h": 60,
                                           "k1": -0.3, "frames": fr})
    v = load_scene(ws, need_masks=False).views[0]
    assert v.image.shape == img.shape and not np.array_equal(v.image, img)
    assert v.dist.size == 0 and v.raw is None  # pinhole from here on
    # the frame's own lens is kept: a render through the pinhole camera is put back onto the frame with it
    np.testing.assert_allclose(v.frame_dist, [-0.3, 0, 0, 0, 0])
    back = to_frame(v.image[..., 0].astype(np.float32), distortion_map(v))
    inner = (slice(10, 50), slice(10, 70))
    moved = np.abs(v.image[..., 0][inner].astype(np.float32) - img[..., 0][inner]).mean()
    assert np.abs(back[inner] - img[..., 0][inner]).mean() < 0.2 * moved, moved
    kept = load_scene(ws, need_masks=False, keep_raw=True).views[0]
    assert np.array_equal(kept.raw, img) and np.array_equal(kept.image, v.image)


def test_each_camera_gets_its_own_lens_map():
    """A model imported with a camera per frame: each frame's prior is moved through its own lens, and frames that
    share a camera share one map."""
    from plantsplat.segment.frame import cached_distortion_map, distortion_map
    from plantsplat.train.data import View

    K = np.array([[60.0, 0, 40], [0, 60, 30], [0, 0, 1]])

    def view(k1, width=80):
        return View(name="f", K=K, viewmat=np.eye(4), width=width, height=60, frame_dist=np.array([k1, 0, 0, 0, 0]))

    cache: dict = {}
    a, b, a2, pin = view(-0.3), view(0.2), view(-0.3), view(0.0)
    ma, mb = cached_distortion_map(a, cache), cached_distortion_map(b, cache)
    assert cached_distortion_map(a2, cache) is ma and cached_distortion_map(pin, cache) is None
    for got, v in ((ma, a), (mb, b)):
        want = distortion_map(v)
        assert all(np.array_equal(g, w) for g, w in zip(got, want))
    assert not np.allclose(ma[0], mb[0])
    wide = cached_distortion_map(view(-0.3, width=100), cache)
    assert wide[0].shape == (60, 100) and len(cache) == 4


def test_omp_waiting_set_before_torch_loads():
    """Importing plantsplat (as the CLI and plantsplat.train do) sets how OpenMP threads wait before torch/numba
    load OpenMP: a short spin (GOMP_SPINCOUNT) on a machine that is not busy, OMP_WAIT_POLICY=PASSIVE on one whose
    load already fills the cores; a user's own setting wins; and it tells when torch came first."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "PLANTSPLAT_OMP_CHOICE")}
    show = ("print(os.environ.get('OMP_WAIT_POLICY'), os.environ.get('GOMP_SPINCOUNT'), "
            "plantsplat.omp_wait_policy_note() is None, plantsplat.omp_setting().split(' (')[1].split()[0])")

    def run(load: float, extra: dict | None = None, first: str = "import plantsplat.cli, plantsplat.train; import torch"):
        code = f"import os, sys; os.getloadavg = lambda: ({load}, 0.0, 0.0); {first}; import plantsplat; {show}"
        return subprocess.run([sys.executable, "-c", code], env={**env, **(extra or {})}, capture_output=True,
                              text=True, check=True).stdout.split()

    cores = os.cpu_count() or 1
    assert run(0.0) == ["None", "20000", "True", "chosen"]
    assert run(cores + 0.5) == ["PASSIVE", "None", "True", "chosen"]
    assert run(0.0, {"OMP_WAIT_POLICY": "ACTIVE"}) == ["ACTIVE", "None", "True", "set"]
    assert run(cores + 0.5, {"GOMP_SPINCOUNT": "500"}) == ["None", "500", "True", "set"]
    # a batch worker inherits its parent's choice (and says so); a user's value beside a stale record is the user's
    chosen = {"GOMP_SPINCOUNT": "20000", "PLANTSPLAT_OMP_CHOICE": "GOMP_SPINCOUNT=20000"}
    assert run(cores + 0.5, chosen) == ["None", "20000", "True", "chosen"]
    assert run(0.0, {**chosen, "GOMP_SPINCOUNT": "500"}) == ["None", "500", "True", "set"]
    assert run(0.0, first="import torch")[:3] == ["None", "20000", "False"]


def test_visual_hull_keeps_an_object_hidden_from_some_views():
    """Random initialisation in object mode: a small box beside the orbit's centre, hidden in 2 of 12
    views by something not in the masks (as the pot hides the cube), still gets initial points; a
    point masked in none of the views does not."""
    import cv2

    from plantsplat.train.data import View, visual_hull_points

    K = np.array([[200.0, 0, 80], [0, 200.0, 60], [0, 0, 1]])
    box = np.array([[x, y, z] for x in (0.6, 1.0) for y in (-0.2, 0.2) for z in (-0.2, 0.2)])  # corners
    views = []
    for k in range(12):
        a = 2 * np.pi * k / 12
        c = 6.0 * np.array([np.cos(a), np.sin(a), 0.0])
        fwd = -c / np.linalg.norm(c)
        right = np.cross(fwd, [0, 0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(fwd, right)
        R = np.stack([right, down, fwd])
        V = np.eye(4)
        V[:3, :3], V[:3, 3] = R, -R @ c
        mask = np.zeros((120, 160), np.uint8)
        mask[:6, :6] = 255  # something else in the masks of every view
        if k not in (3, 4):  # hidden from these two
            uv = (box @ R.T + V[:3, 3]) @ K.T
            uv = uv[:, :2] / uv[:, 2:]
            cv2.fillConvexPoly(mask, cv2.convexHull(uv.astype(np.int32)), 255)
        views.append(View(f"v{k}", K, V, 160, 120, mask=mask))
    center, radius = np.zeros(3), 6.0
    pts = visual_hull_points(views, center, radius, 300, np.random.default_rng(0))
    assert len(pts) >= 100
    lo, hi = box.min(0) - 0.15, box.max(0) + 0.15
    assert ((pts >= lo) & (pts <= hi)).all(axis=1).mean() > 0.95
    strict = visual_hull_points(views, center, radius, 300, np.random.default_rng(0), min_inside=1.0)
    assert len(strict) < len(pts) // 4


def test_points_far_off_or_behind_a_view_are_outside_it_without_a_warning():
    """A random start far from the cameras (imported cameras whose optical axes are nearly parallel put the
    scene's centre 3e7 units away) projected pixel coordinates beyond int64: the cast warned ("invalid value").
    Such points, and those behind the camera or in its plane, are outside; a point in view keeps its pixel."""
    import warnings

    from plantsplat.train.data import View, mean_colors, pixels_hit

    K = np.array([[500.0, 0, 80], [0, 500.0, 60], [0, 0, 1]])
    view = View("v", K, np.eye(4), 160, 120, image=np.full((120, 160, 3), 255, np.uint8))
    pts = np.array([[0.0, 0.0, 2.0], [1e8, 0.0, 1e-12], [0.0, 0.0, -1.0], [1.0, 1.0, 0.0], [np.nan, 0.0, 1.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        inside, u, w = pixels_hit(pts, view)
        colours = mean_colors(pts, [view])
    assert inside.tolist() == [True, False, False, False, False] and (u[0], w[0]) == (80, 60)
    assert colours[0] == pytest.approx([1.0, 1.0, 1.0]) and colours[1:] == pytest.approx(np.full((4, 3), 0.5))


def _ring_views(n: int, K: np.ndarray, mask_fn) -> list:
    from plantsplat.train.data import View

    views = []
    for k in range(n):
        a = 2 * np.pi * k / n
        c = 6.0 * np.array([np.cos(a), np.sin(a), 0.5])
        fwd = -c / np.linalg.norm(c)
        right = np.cross(fwd, [0, 0, 1.0])
        right /= np.linalg.norm(right)
        R = np.stack([right, np.cross(fwd, right), fwd])
        V = np.eye(4)
        V[:3, :3], V[:3, 3] = R, -R @ c
        views.append(View(f"v{k}", K, V, 160, 120, mask=mask_fn(R, V)))
    return views


def test_occluder_points_are_the_unmasked_points_near_the_object():
    """SfM points left out by the masks become occluders only near the masked points: a pot beside
    the plant does, a wall far away does not, nor do the plant's own points."""
    import cv2

    from plantsplat.train.data import Scene, occluder_points

    K = np.array([[200.0, 0, 80], [0, 200.0, 60], [0, 0, 1]])
    rng = np.random.default_rng(0)
    plant = rng.uniform(-0.5, 0.5, (200, 3)) + [0, 0, 0.6]  # the masked object
    pot = rng.uniform(-0.4, 0.4, (100, 3)) * [1, 1, 0.5] + [0, 0, -0.1]  # below it, not masked
    wall = rng.uniform(-1, 1, (100, 3)) * [0.1, 3, 1] + [-4.0, 0, 0]  # far away, not masked

    def mask_fn(R, V):
        m = np.zeros((120, 160), np.uint8)
        uv = (plant @ R.T + V[:3, 3]) @ K.T
        uv = uv[:, :2] / uv[:, 2:]
        cv2.fillConvexPoly(m, cv2.convexHull(uv.astype(np.int32)), 255)
        return m

    views = _ring_views(12, K, mask_fn)
    pts = np.concatenate([plant, pot, wall])
    scene = Scene(views, pts, np.zeros((len(pts), 3), np.uint8), "test")
    occ = occluder_points(scene, views)
    near_pot = np.all(np.abs(occ - [0, 0, -0.1]) <= [0.41, 0.41, 0.21], axis=1)
    assert near_pot.all()  # no wall point, no plant point
    assert len(occ) >= 50  # most of the pot (points the plant's silhouette covers in most views are not)
    empty = Scene(views, np.zeros((0, 3)), np.zeros((0, 3), np.uint8), "test")
    assert len(occluder_points(empty, views)) == 0


def test_occluders_render_as_background_and_hide_what_is_behind():
    """An opaque occluder in front of a red Gaussian, composited over the background, leaves the
    background colour; the model's colours still get gradients, the occluder's opacity too."""
    from plantsplat.train.model import init_params
    from plantsplat.train.render import occluder_tensors, occluders_from, render

    params = init_params(np.array([[0.0, 0.0, 5.0]]), np.array([[1.0, 0.0, 0.0]]), 1, 0.99)
    occ = occluders_from(occluder_tensors(init_params(np.array([[0.0, 0.0, 3.0]]), np.full((1, 3), 0.5), 0, 0.99)), "cpu")
    with torch.no_grad():
        params["scales"].fill_(np.log(0.5))
        occ["scales"].fill_(np.log(0.5))
    K = torch.tensor([[50.0, 0, 16], [0, 50.0, 16], [0, 0, 1]])
    V = torch.eye(4)
    bg = torch.tensor([0.2, 0.7, 0.3])
    alone = render(params, V, K, 32, 32, 1, "cpu", None, bg)
    c = alone.color[16, 16] + (1 - alone.alpha[16, 16]) * bg
    assert c[0] > 0.8  # red
    out = render(params, V, K, 32, 32, 1, "cpu", occ, bg)
    c = out.color[16, 16] + (1 - out.alpha[16, 16]) * bg
    assert torch.allclose(c, bg, atol=0.03)
    assert out.means2d.shape[0] == 2
    (out.color.sum() + out.alpha.sum()).backward()
    assert params["sh0"].grad is not None and occ["opacities"].grad is not None
    assert float(occ["opacities"].grad.abs().sum()) > 0

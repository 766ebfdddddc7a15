"""Training loop on a tiny synthetic capture: loss goes down, background Gaussians vanish in object
mode, metrics are written, export round-trips, an interrupted run resumes, bad input is refused."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from plantsplat.errors import PlantsplatError
from plantsplat.io import read_json, write_json_atomic
from plantsplat.kernel_cache import kernels_cached, mark_kernels_cached
from plantsplat.pipeline import start_kernel_warmup
from plantsplat.train.checkpoint import load_model
from plantsplat.train.config import TrainConfig
from plantsplat.workspace import Workspace

ITERS = 80


def synth_workspace(cap: Path, dst: Path, every: int = 2) -> Workspace:
    """A workspace from a synth capture with its ground-truth poses."""
    from plantsplat.synth.groundtruth import true_transforms

    gt = read_json(cap / "ground_truth.json")
    ws = Workspace(dst)
    ws.images_dir.mkdir(parents=True)
    ws.masks_dir.mkdir(parents=True)
    kept = []
    for index in range(0, len(gt["frames"]), every):
        fr = gt["frames"][index]
        name = Path(fr["file"]).name
        shutil.copy(cap / fr["file"], ws.images_dir / name)
        shutil.copy(cap / fr["mask"], ws.masks_dir / name)
        kept.append((name, index))
    write_json_atomic(ws.transforms_json, true_transforms(gt, kept))
    return ws


@pytest.fixture(scope="module")
def trained(synth_capture, tmp_path_factory):
    """One object-mode run (shared by the tests below), with per-step losses recorded."""
    from plantsplat.train import trainer

    ws = synth_workspace(synth_capture(), tmp_path_factory.mktemp("ws_obj"))
    losses = []
    orig = trainer.photometric_loss

    def spy(color, alpha, bg, gt, lam, gt_alpha=None):  # record the L1 part of each step's loss
        target = gt if gt_alpha is None else gt * gt_alpha + (1 - gt_alpha) * bg
        losses.append(float((color + (1 - alpha) * bg - target).abs().mean().detach()))
        return orig(color, alpha, bg, gt, lam, gt_alpha)

    trainer.photometric_loss = spy
    try:
        summary = trainer.train_workspace(ws, TrainConfig(iterations=ITERS, max_resolution=96, num_downscales=0,
                                                                  init_points=4000, seed=0))
    finally:
        trainer.photometric_loss = orig
    return ws, summary, losses


def test_loss_goes_down_and_metrics_written(trained):
    ws, summary, losses = trained
    assert len(losses) == ITERS
    first, last = np.mean(losses[:20]), np.mean(losses[-20:])  # noisy: a random background each step
    assert last < 0.85 * first, (first, last)
    m = read_json(ws.metrics_json)
    assert m["mode"] == "object" and m["n_test_views"] == len(read_json(ws.train_dir / "split.json")["test"])
    # foreground PSNR from the file agrees with the per-view rows, and is far above a blank render's
    assert m["foreground"]["psnr"] == pytest.approx(np.mean([r["foreground"]["psnr"] for r in m["per_view"]]))
    inner = [r["foreground"]["psnr_interior"] for r in m["per_view"] if r["foreground"]["psnr_interior"] is not None]
    assert inner and m["foreground"]["psnr_interior"] == pytest.approx(np.mean(inner))
    assert m["composite"]["psnr"] > 17.0
    assert m["render_fps"] > 0 and m["n_gaussians"] == summary["n_gaussians"]
    assert m["lpips_weights"] is None or 0.0 < m["composite"]["lpips"] < 1.0
    # test-view renders saved for the report, each next to its ground truth, same size
    from plantsplat.io import read_image

    renders = sorted((ws.train_dir / "renders").glob("*_render.png"))
    test = read_json(ws.train_dir / "split.json")["test"]
    assert 1 <= len(renders) <= min(8, len(test))
    for r in renders:
        stem = r.name[: -len("_render.png")]
        assert f"{stem}.png" in test
        assert read_image(r).shape == read_image(r.with_name(f"{stem}_gt.png")).shape


def test_background_gaussians_vanish(trained):
    """Every Gaussian left projects inside the (dilated) masks of the views that see it."""
    import torch

    from plantsplat.train import data as D
    from plantsplat.train.checkpoint import load_model

    ws, summary, _ = trained
    params, _ = load_model(ws)
    assert float(torch.sigmoid(params["opacities"].detach()).min()) >= 0.1  # culled below the paper's threshold
    scene = D.load_scene(ws, need_masks=True)
    import cv2

    for v in scene.views:
        v.mask = cv2.dilate(v.mask, np.ones((9, 9), np.uint8))
    seen, inside = D.mask_votes(params["means"].detach().numpy().astype(np.float64), scene.views)
    frac_bg = float(((inside < 0.5 * seen) & (seen > 0)).mean())
    assert frac_bg < 0.05, frac_bg


def test_full_mode_keeps_background(trained, tmp_path):
    """The full-frame baseline explains the background with Gaussians: many project outside the masks."""
    import torch

    from plantsplat.train import data as D
    from plantsplat.train.checkpoint import load_model
    from plantsplat.train.trainer import TrainConfig, train_workspace

    ws_obj, _, _ = trained
    ws = Workspace(tmp_path / "ws")
    shutil.copytree(ws_obj.images_dir, ws.images_dir)
    shutil.copytree(ws_obj.masks_dir, ws.masks_dir)
    shutil.copy(ws_obj.transforms_json, ws.transforms_json)
    s = train_workspace(ws, TrainConfig(mode="full", iterations=25, max_resolution=64, num_downscales=0,
                                        init_points=3000))
    m = read_json(ws.metrics_json)
    assert m["pbr"] is not None and m["composite"]["psnr"] > 10
    # the paper's PBR segments the renders as the frames were cut: these masks were copied in, not segmented
    # here, so there is no segmenter's object to cut the renders with, and the metrics say so
    assert m["pbr_segmented"] is None and "plantsplat segment" in m["pbr_segmented_error"]
    params, _ = load_model(ws)
    scene = D.load_scene(ws, need_masks=True, load_images=True)
    seen, inside = D.mask_votes(params["means"].detach().numpy().astype(np.float64), scene.views)
    assert float(((inside == 0) & (seen > 0)).mean()) > 0.3
    assert s["n_gaussians"] == params["means"].shape[0] and torch.isfinite(params["means"]).all()


def test_segmented_pbr_needs_the_segment_stages_object(tmp_path):
    """The paper's PBR segments the full model's renders as the frames were cut (the segment stage's 3D object,
    test_segment checks that on a capture); a workspace without that object (masks imported) gets no
    pbr_segmented and a reason, and nothing is written into it."""
    from plantsplat.train.evaluate import segment_renders

    ws = Workspace(tmp_path / "ws")
    ws.root.mkdir()
    masks, err = segment_renders(ws, {"frame_00000.png": np.zeros((8, 8, 3), np.uint8)})
    assert masks is None and "plantsplat segment" in err
    assert not any(ws.root.iterdir())


def test_export_round_trip(trained):
    import torch
    from plyfile import PlyData

    from plantsplat.export import ExportConfig
    from plantsplat.export import stage as model_export
    from plantsplat.pipeline import export_stage
    from plantsplat.ply import read_splat as read_splat_ply
    from plantsplat.train.checkpoint import load_model

    ws, _, _ = trained
    info = model_export.run(ws)
    params, _ = load_model(ws)
    g = read_splat_ply(ws.splat_ply)
    for k in ("means", "scales", "opacities", "sh0", "shN"):
        np.testing.assert_allclose(g[k], params[k].detach().numpy(), rtol=1e-6, atol=1e-6)
    q = torch.nn.functional.normalize(params["quats"].detach(), dim=-1).numpy()
    np.testing.assert_allclose(g["quats"], q, atol=1e-6)
    v = PlyData.read(str(ws.points_ply))["vertex"]
    assert v.data.dtype.names == ("x", "y", "z", "red", "green", "blue", "opacity", "scale_0", "scale_1", "scale_2")
    assert len(v.data) == info["n_points"] and (np.asarray(v["opacity"]) >= 0.1).all()
    export_stage(ws, ExportConfig())
    stamp = ws.splat_ply.stat().st_mtime_ns
    assert export_stage(ws, ExportConfig())["up_to_date"] and ws.splat_ply.stat().st_mtime_ns == stamp
    ws.splat_ply.write_bytes(ws.splat_ply.read_bytes()[:100])  # a truncated export is written again (issue 34)
    assert not export_stage(ws, ExportConfig()).get("up_to_date")
    assert len(read_splat_ply(ws.splat_ply)["means"]) == len(g["means"])


def test_resume_after_interrupt(synth_capture, tmp_path, monkeypatch, interrupted_after):
    from plantsplat.pipeline import train_stage
    from plantsplat.train import trainer
    from plantsplat.train.checkpoint import load_checkpoint

    ws = synth_workspace(synth_capture(), tmp_path / "ws", every=4)
    cfg = TrainConfig(iterations=16, max_resolution=64, num_downscales=0, checkpoint_seconds=0,
                              evaluate=False, init_points=2000)
    real_render = trainer.render
    monkeypatch.setattr(trainer, "render", interrupted_after(real_render, 8))
    with pytest.raises(KeyboardInterrupt):
        train_stage(ws, cfg)
    ck = load_checkpoint(ws.root / ".train.partial" / "checkpoint.pt")
    assert ck["step"] == 7 and not (ws.train_dir / "model.pt").exists()
    monkeypatch.setattr(trainer, "render", real_render)
    s = train_stage(ws, cfg)
    assert s["resumed"] is True and s["iterations"] == 16
    assert (ws.train_dir / "model.pt").is_file() and not (ws.train_dir / "checkpoint.pt").exists()
    assert not (ws.root / ".train.partial").exists()
    # a finished model is not retrained; other options train afresh (never from the other run's files)
    assert train_stage(ws, cfg)["up_to_date"]
    other = train_stage(ws, TrainConfig(mode="full", iterations=16, max_resolution=64, num_downscales=0, evaluate=False))
    assert other["resumed"] is False and other["mode"] == "full"


def test_retraining_keeps_the_finished_model_until_the_new_one_is_complete(synth_capture, tmp_path, monkeypatch,
                                                                             interrupted_after):
    """Issue 42 #2: a finished model re-trained with other options, then interrupted or failed, is still there
    (model.pt, split.json, metrics.json as they were); the new run, once complete, replaces them whole."""
    from plantsplat.io import write_image_atomic
    from plantsplat.pipeline import train_stage
    from plantsplat.train import trainer

    ws = synth_workspace(synth_capture(), tmp_path / "ws", every=6)
    small = {"max_resolution": 96, "num_downscales": 0, "checkpoint_seconds": 0, "init_points": 500}
    train_stage(ws, TrainConfig(iterations=6, **small))
    kept = {p: p.read_bytes() for p in (ws.train_dir / "model.pt", ws.train_dir / "split.json", ws.metrics_json)}
    real_render = trainer.render
    monkeypatch.setattr(trainer, "render", interrupted_after(real_render, 4))
    with pytest.raises(KeyboardInterrupt):
        train_stage(ws, TrainConfig(iterations=8, **small))
    assert {p: p.read_bytes() for p in kept} == kept
    monkeypatch.setattr(trainer, "render", real_render)
    bad = ws.image_names()[0]
    good_mask = (ws.masks_dir / bad).read_bytes()
    write_image_atomic(ws.masks_dir / bad, np.zeros((10, 10), np.uint8))  # a corrupt mask: the forced run fails
    with pytest.raises(PlantsplatError, match="segment"):
        train_stage(ws, TrainConfig(iterations=8, **small), force=True)
    assert {p: p.read_bytes() for p in kept} == kept
    (ws.masks_dir / bad).write_bytes(good_mask)
    s = train_stage(ws, TrainConfig(iterations=8, **small))
    assert s["iterations"] == 8 and load_model(ws)[1]["config"]["iterations"] == 8
    assert read_json(ws.metrics_json)["iterations"] == 8
    assert not (ws.root / ".train.partial").exists() and not (ws.root / ".train.old").exists()


def test_sigterm_takes_the_ctrl_c_path_and_the_run_resumes(synth_capture, tmp_path):
    """Issue 42 #7: SIGTERM (kill, timeout, a scheduler) to `plantsplat train` ends it like Ctrl-C: exit 143, one line,
    the stage record left `running` with its checkpoint, the lock released; the same command then resumes."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from plantsplat.pipeline import train_stage
    from plantsplat.stages import read_record

    ws = synth_workspace(synth_capture(), tmp_path / "ws", every=4)
    args = ["--iterations", "400", "--max-resolution", "64", "--num-downscales", "0", "--checkpoint-seconds", "0",
            "--init-points", "500", "--no-evaluate"]
    proc = subprocess.Popen([sys.executable, "-m", "plantsplat", "train", str(ws.root), *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PLANTSPLAT_NO_PROGRESS": "1"})
    ckpt = ws.root / ".train.partial" / "checkpoint.pt"
    deadline = time.monotonic() + 60
    while not any(p.exists() for p in (ckpt, ws.train_dir / "checkpoint.pt")) and proc.poll() is None \
            and time.monotonic() < deadline:
        time.sleep(0.02)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, (out, err)
    said = [ln for ln in (out + err).splitlines() if ln.strip() and not ln.startswith(("INFO", " "))]
    assert said == ["terminated (SIGTERM): finished outputs are kept; re-run the same command to resume"], out + err
    assert "Traceback" not in err and "Fatal" not in err
    assert read_record(ws, "train")["status"] == "running" and ckpt.is_file()
    assert not (ws.root / ".plantsplat" / "lock").exists()
    cfg = TrainConfig(iterations=400, max_resolution=64, num_downscales=0, checkpoint_seconds=0, init_points=500,
                      evaluate=False)
    s = train_stage(ws, cfg)
    assert s["resumed"] is True and (ws.train_dir / "model.pt").is_file()


def test_nan_loss_stops_and_keeps_checkpoint(synth_capture, tmp_path, monkeypatch):
    import torch

    from plantsplat.train import trainer

    ws = synth_workspace(synth_capture(), tmp_path / "ws", every=4)
    real_render = trainer.render
    calls = {"n": 0}

    def poisoned(*a, **k):
        out = real_render(*a, **k)
        calls["n"] += 1
        if calls["n"] >= 5:
            out.color = out.color * torch.tensor(float("nan"))
        return out

    monkeypatch.setattr(trainer, "render", poisoned)
    cfg = TrainConfig(iterations=10, max_resolution=64, num_downscales=0, checkpoint_seconds=0,
                              evaluate=False, init_points=2000)
    with pytest.raises(PlantsplatError, match="NaN.*checkpoint \\(step 4\\)"):
        trainer.train_workspace(ws, cfg)
    assert (ws.root / ".train.partial" / "checkpoint.pt").is_file()


def _nan_patch(g):
    """A gradient hook: NaN in a 4x4 patch at the centre of an image gradient [H, W, 3]."""
    g = g.clone()
    h, w = g.shape[0] // 2, g.shape[1] // 2
    g[h - 2:h + 2, w - 2:w + 2] = float("nan")
    return g


def _poison_grads(monkeypatch, trainer, steps):
    """Make the renders of the given (0-based) training steps back-propagate NaN through a few pixels."""
    real_render = trainer.render
    calls = {"n": 0}

    def poisoned(*a, **k):
        out = real_render(*a, **k)
        if calls["n"] in steps:
            out.color.register_hook(_nan_patch)
        calls["n"] += 1
        return out

    monkeypatch.setattr(trainer, "render", poisoned)


def test_nan_gradients_are_skipped_and_counted(synth_capture, tmp_path, monkeypatch):
    """A step whose gradient is NaN for a few pixels (the loss finite) skips the update of the Gaussians drawn
    there: training finishes with a finite model and reports the step; without the guard Adam wrote NaN into
    their means and the next render stopped the run."""
    import torch

    from plantsplat.train import trainer

    ws = synth_workspace(synth_capture(), tmp_path / "ws", every=4)
    _poison_grads(monkeypatch, trainer, {3})
    cfg = TrainConfig(iterations=10, max_resolution=64, num_downscales=0, evaluate=False, init_points=2000)
    s = trainer.train_workspace(ws, cfg)
    assert s["nonfinite_grad_steps"] == 1 and s["nonfinite_grad_gaussians"] > 0
    params, _ = load_model(ws)
    assert all(bool(torch.isfinite(v).all()) for v in params.values())


def test_all_threads_means_the_cores_the_process_may_use(synth_capture, tmp_path, monkeypatch):
    """``threads=0`` gives torch the cores the process may use (a batch worker's share), not every core."""
    import torch

    from plantsplat.train import trainer

    ws = synth_workspace(synth_capture(), tmp_path / "ws", every=4)
    monkeypatch.setenv("NUMBA_NUM_THREADS", "1")  # what `plantsplat batch` sets in a worker with one core
    asked = []
    monkeypatch.setattr(torch, "set_num_threads", asked.append)  # OpenMP's count is per thread: record the call
    trainer.train_workspace(ws, TrainConfig(iterations=2, max_resolution=64, num_downscales=0, evaluate=False,
                                            init_points=500, threads=0))
    assert asked == [1]


def test_nan_gradients_that_persist_stop_the_run(synth_capture, tmp_path, monkeypatch):
    from plantsplat.train import trainer

    ws = synth_workspace(synth_capture(), tmp_path / "ws", every=4)
    _poison_grads(monkeypatch, trainer, set(range(2, 100)))
    monkeypatch.setattr(trainer, "MAX_NONFINITE_RUN", 3)
    cfg = TrainConfig(iterations=10, max_resolution=64, num_downscales=0, evaluate=False, init_points=2000)
    with pytest.raises(PlantsplatError, match="gradients were NaN/inf 3 steps in a row"):
        trainer.train_workspace(ws, cfg)


def test_bad_inputs(synth_capture, tmp_path):
    from plantsplat.train.trainer import TrainConfig, train_workspace

    ws = synth_workspace(synth_capture(), tmp_path / "ws", every=6)
    cfg = TrainConfig(iterations=5, evaluate=False, max_resolution=80)
    name = ws.image_names()[0]
    (ws.masks_dir / name).unlink()
    with pytest.raises(PlantsplatError, match=f"{name}: missing mask"):
        train_workspace(ws, cfg)
    ws.transforms_json.unlink()
    with pytest.raises(PlantsplatError, match="no camera poses"):
        train_workspace(ws, cfg)
    empty = Workspace(tmp_path / "empty")
    with pytest.raises(PlantsplatError, match="plantsplat frames"):
        train_workspace(empty, cfg)


def test_mismatched_mask_size(synth_capture, tmp_path):
    from plantsplat.io import write_image_atomic
    from plantsplat.train.trainer import TrainConfig, train_workspace

    ws = synth_workspace(synth_capture(), tmp_path / "ws", every=6)
    name = ws.image_names()[1]
    write_image_atomic(ws.masks_dir / name, np.zeros((10, 10), np.uint8))
    with pytest.raises(PlantsplatError, match="re-run `plantsplat segment"):
        train_workspace(ws, TrainConfig(iterations=5, evaluate=False))


def test_cli_errors_are_one_line(tmp_path, capsys):
    from plantsplat.cli import main

    assert main(["train", str(tmp_path / "nope")]) == 2
    assert main(["export", str(tmp_path)]) != 0
    err = capsys.readouterr()
    text = err.out + err.err
    assert "Traceback" not in text and "no trained model" in text


def test_occluders_from_sfm_points_resume_and_stay_out_of_the_export(synth_capture, tmp_path, monkeypatch):
    """With SfM points (here: points of the synthetic scene, pot and platform included) object mode
    adds occluders; they survive an interrupted run, are stored beside the model and the export
    holds only the model's own Gaussians."""
    from plantsplat.export import stage as model_export
    from plantsplat.pipeline import train_stage
    from plantsplat.ply import read_splat as read_splat_ply
    from plantsplat.train import trainer
    from plantsplat.train.checkpoint import load_checkpoint
    from plantsplat.train.data import sparse_points as read_ply_points

    cap = synth_capture()
    ws = synth_workspace(cap, tmp_path / "ws", every=4)
    pts, cols = read_ply_points(cap / "scene_gt.ply")
    pick = np.random.default_rng(0).permutation(len(pts))[:3000]
    from plyfile import PlyData, PlyElement

    v = np.zeros(len(pick), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for i, c in enumerate("xyz"):
        v[c] = pts[pick, i]
    for i, c in enumerate(("red", "green", "blue")):
        v[c] = cols[pick, i]
    PlyData([PlyElement.describe(v, "vertex")]).write(str(ws.sparse_points_ply))
    cfg = TrainConfig(iterations=16, max_resolution=64, num_downscales=0, checkpoint_seconds=0, evaluate=False)
    real_render = trainer.render
    calls = {"n": 0, "occ": 0}

    def flaky(*a, **k):
        calls["n"] += 1
        if calls["n"] == 8:
            raise KeyboardInterrupt
        if len(a) > 7 and a[7] is not None:
            calls["occ"] = int(a[7]["means"].shape[0])
        return real_render(*a, **k)

    monkeypatch.setattr(trainer, "render", flaky)
    with pytest.raises(KeyboardInterrupt):
        train_stage(ws, cfg)
    n_occ = calls["occ"]
    assert n_occ >= 20
    ck = load_checkpoint(ws.root / ".train.partial" / "checkpoint.pt")
    assert ck["extra"]["occluders"]["means"].shape[0] == n_occ
    calls["occ"] = 0
    s = train_stage(ws, cfg)
    assert s["resumed"] is True and calls["occ"] == n_occ  # the resumed run renders the same occluders
    model = load_checkpoint(ws.train_dir / "model.pt")
    assert 0 < model["extra"]["occluders"]["means"].shape[0] <= n_occ
    model_export.run(ws)
    g = read_splat_ply(ws.splat_ply)
    assert len(g["means"]) == s["n_gaussians"] == model["params"]["means"].shape[0]


def test_the_warmup_reaches_every_kernel_signature_the_stages_use(synth_capture, tmp_path):
    """plantsplat.train.warmup compiles the CPU kernels before a run needs them: only if it calls each with the
    argument types the stages use does the stage find it cached. After the warm-up, an object-mode training with its
    crops and evaluation, a full-mode training and the segment stage's priors add no signature
    (tests/warmup_coverage.py; with the object-mode part of the warm-up taken out it lists the training kernels)."""
    ws = synth_workspace(synth_capture(), tmp_path / "ws")
    script = Path(__file__).with_name("warmup_coverage.py")
    out = subprocess.run([sys.executable, str(script), str(ws.root)], capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-2000:]
    assert json.loads(out.stdout.strip().splitlines()[-1]) == {}


def test_the_kernel_warmup_starts_once_per_process_and_leaves_its_stamp(monkeypatch):
    """Where the kernels are not known to be cached, `plantsplat run` and `plantsplat demo` start the warm-up (a demo,
    which runs the pipeline, starts one); it ends by itself and leaves the stamp that keeps later runs from starting
    it."""
    from plantsplat import pipeline

    monkeypatch.setattr(pipeline, "kernels_cached", lambda: False)
    first = start_kernel_warmup()
    assert first is not None and start_kernel_warmup() is first
    assert first.wait(timeout=900) == 0
    assert kernels_cached()


def test_every_cached_kernel_module_is_in_the_stamp():
    """A kernel module left out of the stamp's digest would let a changed kernel pass for a cached one: the first run
    after an update would compile it inside a stage, on one core, instead of in the warm-up."""
    from plantsplat import kernel_cache

    raster = Path(kernel_cache.__file__).with_name("raster")
    cached = {p.name for p in raster.glob("*.py") if "cache=True" in p.read_text()}
    assert cached and cached <= set(kernel_cache.KERNEL_MODULES)


def test_the_kernel_stamp_changes_where_numba_drops_its_cached_kernels(tmp_path, monkeypatch):
    """numba's cache of a file's kernels is dropped when the file's time or size changes (a reinstall, a checkout
    there and back) and is kept per processor: the stamp follows, so the warm-up runs again there."""
    import os
    import shutil

    from plantsplat import kernel_cache

    raster = tmp_path / "raster"
    shutil.copytree(Path(kernel_cache.__file__).with_name("raster"), raster)
    before = kernel_cache.kernel_sources_digest(raster)
    assert kernel_cache.kernel_sources_digest(raster) == before
    st = (raster / "cpu.py").stat()
    os.utime(raster / "cpu.py", ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))  # the same source, touched
    touched = kernel_cache.kernel_sources_digest(raster)
    assert touched != before
    monkeypatch.setattr(kernel_cache, "processor_model", lambda: "another processor")
    assert kernel_cache.kernel_sources_digest(raster) != touched


def test_the_kernel_stamp_belongs_to_one_numba_cache_and_one_version_of_the_kernels(tmp_path, monkeypatch):
    from plantsplat import kernel_cache

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    assert not kernels_cached()
    mark_kernels_cached()
    assert kernels_cached()
    monkeypatch.setattr(kernel_cache, "KERNEL_MODULES", kernel_cache.KERNEL_MODULES[:-1])  # other kernel sources
    assert not kernels_cached()
    monkeypatch.undo()
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "emptied"))  # the cache deleted, or another one
    assert not kernels_cached()
    monkeypatch.setattr(kernel_cache, "KERNEL_MODULES", ("no_such_module.py",))  # sources numba could not cache
    assert kernels_cached()

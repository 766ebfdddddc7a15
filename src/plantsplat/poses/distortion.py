"""Whether a capture's frames support the camera model's lens distortion (model selection on the mapped model).

COLMAP fits a shared camera with radial distortion (``RADIAL``: k1, k2) to every capture. Where the lens has none
to speak of (a phone's video is usually corrected in the phone; a render has none), the two coefficients are not
held by the data: an orbit of frames lets them trade against the focal length, and so against the cameras'
distance from the plant. On independent renders with no distortion, k1 came out at 0.007-0.011 and the focal
length 0.7-1.8 % long, which put the cameras 0.7-2.7 % too far out.

:func:`choose_distortion` bundle-adjusts the mapped model twice from the same start, with the distortion free and
with it zero, and keeps the distortion only where the Bayesian information criterion (BIC) says the frames need it:
the errors' likelihood under the bundle adjustment's Cauchy loss must gain more than ``p ln n`` for ``n``
observations and ``p`` distortion coefficients (Schwarz 1978). The two run side by side, the second in a child forked
from the stage (:func:`plantsplat.workers.start_forked`), whose adjusted values are put back into the stage's copy:
the result is, to the bit, that of the two made one after the other. Both adjustments use that robust loss
(:func:`plantsplat.poses.sfm.final_ba_options`): with plain least squares the few matches left off by pixels pulled
the focal length (a render's 1.8 % long, 0.5 % with the loss).

Usage:
    rec, kept = choose_distortion(rec, num_threads=1, loss_scale_px=1.0, report=report)
    refine_with_cube(rec, ..., refine_distortion=kept)
"""

from __future__ import annotations

import math
import time

import numpy as np
import pycolmap

from plantsplat.log import get_logger
from plantsplat.poses.sfm import final_ba_options
from plantsplat.workers import start_forked

log = get_logger(__name__)

BA_ITERATIONS = 100
"""Iterations of each trial bundle adjustment (both converge in far fewer on a mapped model)."""

NO_DISTORTION = {"SIMPLE_PINHOLE", "PINHOLE"}

FORK_TIMEOUT_FACTOR = 5.0
"""The pinhole adjustment runs in a forked child beside the adjustment with distortion
(:func:`plantsplat.workers.start_forked`): a child that has given nothing this many times the other's seconds (and
at least :data:`FORK_TIMEOUT_MIN_S`) later is ended, and the pinhole adjustment made in the stage's process."""

FORK_TIMEOUT_MIN_S = 60.0
"""The least wait for the forked pinhole adjustment. Started with the distortion set to zero, it can run all its
iterations where the adjustment with distortion, started from the mapped model, ends after one (a synthetic model
of 30 frames through a k1 = 0.08 lens: 5.4 s against 0.08 s); ending it then would do it twice. The wait guards
only against a child stuck at its start."""


def bundle_adjust(rec, refine_distortion: bool, num_threads: int, loss_scale_px: float) -> tuple[float, int]:
    """Bundle adjustment of every registered frame of ``rec`` in place (:func:`plantsplat.poses.sfm.final_ba_options`);
    returns the final cost (Ceres': half the sum of the Cauchy loss of each squared reprojection error) and the number
    of observations."""
    config = pycolmap.BundleAdjustmentConfig()
    for im in rec.images.values():
        if im.has_pose:
            config.add_image(im.image_id)
    opts = final_ba_options(refine_distortion, num_threads, loss_scale_px, BA_ITERATIONS)
    summary = pycolmap.create_default_bundle_adjuster(opts, config, rec).solve()
    return float(summary.ceres_summary.final_cost), int(summary.num_residuals) // 2


def _adjusted(zero, num_threads: int, loss_scale_px: float) -> tuple[float, dict]:
    """The pinhole adjustment of :func:`choose_distortion`: its cost and the values it gave (:func:`adjusted_values`)."""
    cost, _ = bundle_adjust(zero, False, num_threads, loss_scale_px)
    return cost, adjusted_values(zero)


def adjusted_values(rec) -> dict:
    """What a bundle adjustment changes in ``rec``: each camera's parameters, each posed frame's pose (rig from
    world: quaternion xyzw, translation) and each point's position, as float64 arrays by id."""
    return {"cameras": {i: np.array(c.params, np.float64) for i, c in rec.cameras.items()},
            "frames": {i: np.array(f.rig_from_world.params, np.float64) for i, f in rec.frames.items() if f.has_pose},
            "points": {i: np.array(p.xyz, np.float64) for i, p in rec.points3D.items()}}


def set_values(rec, values: dict) -> None:
    """Put :func:`adjusted_values` of an adjusted copy of ``rec`` into ``rec``, bit for bit."""
    for i, params in values["cameras"].items():
        rec.cameras[i].params = params
    for i, q_t in values["frames"].items():
        rec.frames[i].rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(q_t[:4]), q_t[4:])
    for i, xyz in values["points"].items():
        rec.points3D[i].xyz = xyz


def distortion_params(camera) -> list[int]:
    """Indices of the distortion coefficients in ``camera.params`` (none for the pinhole models)."""
    if camera.model.name in NO_DISTORTION:
        return []
    return list(camera.extra_params_idxs())


def without_distortion(rec):
    """A copy of ``rec`` with every camera's distortion coefficients set to zero."""
    out = pycolmap.Reconstruction(rec)
    for cam in out.cameras.values():
        params = np.array(cam.params, dtype=np.float64)
        params[distortion_params(cam)] = 0.0
        cam.params = params
    return out


def bic_gain(cost_zero: float, cost_free: float, n: int, p: int, loss_scale_px: float) -> float:
    """How much lower the BIC of the model with ``p`` distortion coefficients is than the pinhole's (positive: the
    frames need the distortion), from the two bundle adjustments' final costs over ``n`` observations.

    Ceres' cost with a Cauchy loss of scale ``a`` is ``C = 1/2 sum a^2 ln(1 + r^2/a^2)``: the errors' negative
    log-likelihood under that loss is ``2 C / a^2`` (up to a constant), and BIC = 2 NLL + p ln n."""
    return 4.0 * (cost_zero - cost_free) / loss_scale_px**2 - p * math.log(n)


def choose_distortion(rec, num_threads: int, loss_scale_px: float, report: dict):
    """``rec`` bundle-adjusted with the distortion its camera model has, or a copy adjusted with none where the
    frames do not support it (:func:`bic_gain`). Returns ``(model, kept)``; ``report["distortion"]`` says why."""
    cams = list(rec.cameras.values())
    p = sum(len(distortion_params(c)) for c in cams)
    if p == 0 or rec.num_points3D() == 0:
        return rec, p > 0
    zero = without_distortion(rec)
    beside = start_forked(lambda: _adjusted(zero, num_threads, loss_scale_px))
    try:
        t0 = time.perf_counter()
        cost_free, n = bundle_adjust(rec, True, num_threads, loss_scale_px)
        waited = FORK_TIMEOUT_FACTOR * (time.perf_counter() - t0)
        cost_zero, values = beside.result(timeout=max(waited, FORK_TIMEOUT_MIN_S))
    finally:
        beside.stop()
    gain = bic_gain(cost_zero, cost_free, n, p, loss_scale_px)
    kept = gain > 0
    report["distortion"] = {"kept": kept, "bic_gain": round(gain, 2), "observations": n,
                            "fitted": [float(v) for c in cams for v in np.asarray(c.params)[distortion_params(c)]]}
    if not kept:
        set_values(zero, values)  # the child's adjustment (the same values when it ran here)
        report["events"].append("lens distortion left out: the frames do not support it (BIC)")
    log.info("poses: lens distortion %s (BIC gain %.1f)", "fitted" if kept else "left out, not supported by the frames",
             gain)
    return (rec if kept else zero), kept

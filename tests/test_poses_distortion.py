"""The lens distortion is fitted where the frames need it and left out where they do not (BIC)."""

from __future__ import annotations

import math

import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap")

from plantsplat.poses.distortion import bic_gain, bundle_adjust, choose_distortion, without_distortion  # noqa: E402

W, H, F = 540, 960, 700.0


def look_at(eye, target):
    """Camera-to-world (OpenCV axes) at ``eye`` looking at ``target`` with world +z up."""
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    M = np.eye(4)
    M[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
    M[:3, 3] = eye
    return M


def radial(xy: np.ndarray, k1: float, k2: float) -> np.ndarray:
    """COLMAP's RADIAL distortion of normalised image points ``[N, 2]``."""
    r2 = (xy**2).sum(1, keepdims=True)
    return xy * (1 + k1 * r2 + k2 * r2**2)


def orbit_model(k1: float, k2: float, seed: int, noise_px: float = 0.5):
    """A RADIAL model of 36 cameras on three rings around 600 points (a plant-sized box and a far wall), whose
    observations are the true projections through a lens with ``k1, k2`` plus pixel noise; the model's camera
    starts with the focal length 1 % long and no distortion."""
    rng = np.random.default_rng(seed)
    pts = np.concatenate([rng.uniform([-20, -20, 0], [20, 20, 40], (400, 3)),
                          np.c_[rng.uniform(-150, 150, (200, 2)), rng.uniform(0, 120, 200)] * [1, 0, 1] + [0, 160, 0]])
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera.create_from_model_name(1, "RADIAL", 1.01 * F, W, H)
    rec.add_camera_with_trivial_rig(cam)
    tracks = [pycolmap.Track() for _ in pts]
    for i in range(36):
        a = 2 * np.pi * (i % 12) / 12 + 0.1 * (i // 12)
        eye = np.array([50 * np.cos(a), 50 * np.sin(a), [10.0, 25.0, 45.0][i // 12]])
        w2c = np.linalg.inv(look_at(eye, np.array([0, 0, 15.0])))
        Xc = pts @ w2c[:3, :3].T + w2c[:3, 3]
        xy = radial(Xc[:, :2] / Xc[:, 2:], k1, k2) * F + [W / 2, H / 2] + rng.normal(0, noise_px, (len(pts), 2))
        seen = np.flatnonzero((Xc[:, 2] > 1) & (xy[:, 0] > 0) & (xy[:, 0] < W) & (xy[:, 1] > 0) & (xy[:, 1] < H))
        im = pycolmap.Image(name=f"frame_{i:05d}.png", keypoints=xy[seen], camera_id=1, image_id=i + 1)
        rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(w2c[:3, :]))
        for j, p in enumerate(seen):
            tracks[p].add_element(i + 1, j)
    for X, track in zip(pts, tracks):
        if track.length() >= 2:
            rec.add_point3D(X.reshape(3, 1), track, np.zeros(3, np.uint8))
    return rec


def test_bic_gain_weighs_the_fit_against_the_coefficients():
    n = 10_000
    assert bic_gain(1000.0, 1000.0, n, 2, 1.0) == pytest.approx(-2 * math.log(n))
    assert bic_gain(1010.0, 1000.0, n, 2, 1.0) > 0  # 1 % lower cost over 10,000 observations: needed
    assert bic_gain(1001.0, 1000.0, n, 2, 1.0) < 0  # a tenth of a percent: not
    assert bic_gain(1010.0, 1000.0, n, 2, 2.0) < bic_gain(1010.0, 1000.0, n, 2, 1.0)  # a wider loss: weaker evidence


@pytest.mark.parametrize("seed", [0, 1])
def test_no_distortion_in_the_frames_none_in_the_model(seed):
    report = {"events": []}
    rec, kept = choose_distortion(orbit_model(0.0, 0.0, seed), 1, 1.0, report)
    cam = next(iter(rec.cameras.values()))
    assert not kept and not report["distortion"]["kept"]
    assert list(cam.params[3:]) == [0.0, 0.0]
    assert cam.params[0] == pytest.approx(F, rel=0.005)
    assert any("distortion left out" in e for e in report["events"])


@pytest.mark.parametrize("seed", [0, 1])
def test_a_lens_with_distortion_keeps_it(seed):
    report = {"events": []}
    rec, kept = choose_distortion(orbit_model(-0.08, 0.02, seed), 1, 1.0, report)
    cam = next(iter(rec.cameras.values()))
    assert kept and report["distortion"]["bic_gain"] > 0
    assert cam.params[3] == pytest.approx(-0.08, abs=0.01)
    assert cam.params[0] == pytest.approx(F, rel=0.005)


def test_a_pinhole_model_is_left_as_it_is():
    rec = orbit_model(0.0, 0.0, 0)
    pin = pycolmap.Reconstruction(rec)
    cam = next(iter(pin.cameras.values()))
    pin.cameras[1] = pycolmap.Camera.create_from_model_name(1, "PINHOLE", cam.params[0], W, H)
    report = {"events": []}
    out, kept = choose_distortion(pin, 1, 1.0, report)
    assert out is pin and not kept and "distortion" not in report


def _model_bytes(rec, folder) -> dict[str, bytes]:
    folder.mkdir()
    rec.write(str(folder))
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


@pytest.mark.parametrize("k1, k2", [(0.0, 0.0), (-0.08, 0.02)])
def test_side_by_side_adjustments_give_the_model_of_one_after_the_other(k1, k2, tmp_path):
    """The pinhole adjustment runs in a forked child beside the one with distortion: the model and the BIC gain are
    those of the two adjustments made one after the other in this process, to the bit (the demo's results must not
    depend on how the stage was scheduled)."""
    rec = orbit_model(k1, k2, 0)
    report = {"events": []}
    out, kept = choose_distortion(pycolmap.Reconstruction(rec), 1, 1.0, report)
    free, zero = pycolmap.Reconstruction(rec), without_distortion(rec)
    cost_free, n = bundle_adjust(free, True, 1, 1.0)
    cost_zero, _ = bundle_adjust(zero, False, 1, 1.0)
    assert kept == (k1 != 0.0)
    assert report["distortion"]["bic_gain"] == round(bic_gain(cost_zero, cost_free, n, 2, 1.0), 2)
    assert _model_bytes(out, tmp_path / "side") == _model_bytes(free if kept else zero, tmp_path / "sequential")

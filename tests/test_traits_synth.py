"""Traits of `plantsplat synth` ground-truth clouds equal the synthetic ground truth (a unit test of
the measurement itself: the clouds are exact surface samples, so every trait must be within 1 %)."""

from __future__ import annotations

import json

import pytest
from scipy.spatial.transform import Rotation

from plantsplat.ply import read_point_cloud as read_points_ply
from plantsplat.traits.measure import measure_traits

GEOMETRIC = ("height_cm", "width1_cm", "width2_cm", "canopy_volume_cm3", "canopy_area_cm2")


@pytest.fixture(scope="module")
def capture(synth_capture):
    cap = synth_capture()
    gt = json.loads((cap / "ground_truth.json").read_text())
    return cap, gt


def _check(traits, gt, tol=0.01, soil_known=True):
    """Every geometric trait within ``tol``; without the soil the height is the plant's extent."""
    for k in GEOMETRIC:
        want = gt[k] if soil_known or k != "height_cm" else gt["height_extent_cm"]
        assert traits[k] == pytest.approx(want, rel=tol), k
    assert traits["height_extent_cm"] == pytest.approx(gt["height_extent_cm"], rel=tol)


def test_scene_ground_truth_cloud_gives_ground_truth_traits(capture):
    cap, gt = capture
    scene = read_points_ply(cap / "scene_gt.ply")
    res = measure_traits(scene["xyz"], scene["rgb"], calibrated=True, soil_z=gt["plant"]["soil_z_cm"])
    assert res.quality == "ok", res.reasons
    _check(res.traits, gt)
    # the cube was found and measured by its planes
    assert res.scale["cube_edge_cm_planes"] == pytest.approx(10.0, rel=0.01)
    assert res.scale["cube_tilt_deg"] < 1.0
    # fruit: the colour model counts ripe (red) fruit; two touching fruit count as one
    ripe = sum(bool(f["ripe"]) for f in gt["plant"]["fruits"])
    assert ripe - 1 <= res.traits["fruit_count"] <= ripe
    assert res.traits["fruit_count"] >= 1 or ripe == 0


def test_unscaled_scene_is_calibrated_by_the_cube(capture):
    cap, gt = capture
    scene = read_points_ply(cap / "scene_gt.ply")
    R = Rotation.random(random_state=3).as_matrix()
    cloud = (scene["xyz"] @ R.T) * 0.37 + [10.0, -4.0, 7.0]
    res = measure_traits(cloud, scene["rgb"], calibrated=False)
    assert res.quality in ("ok", "warning"), res.reasons
    assert res.scale["source"] == "cube_planes"
    assert res.scale["scale"] * 0.37 == pytest.approx(1.0, rel=0.01)
    _check(res.traits, gt, soil_known=False)  # an uncalibrated cloud's soil is not known
    # the calibrated frame: ground at z = 0 under the cube, so the plant is above it
    assert res.plant_points[:, 2].min() > -0.1


def test_plant_cloud_without_cube_is_measured_and_flagged(capture):
    cap, gt = capture
    plant = read_points_ply(cap / "plant_gt.ply")
    res = measure_traits(plant["xyz"], plant["rgb"], calibrated=True, soil_z=gt["plant"]["soil_z_cm"])
    assert res.quality == "warning" and any("no cube" in r for r in res.reasons)
    _check(res.traits, gt)

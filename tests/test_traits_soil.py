"""The soil in a pot from the SfM points (:mod:`plantsplat.segment.soil`), and the traits stage measuring from it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from plantsplat.ply import write_point_cloud
from plantsplat.segment.object3d import pot_soil_layer
from plantsplat.traits.checks import workspace_soil
from plantsplat.workspace import Workspace

CENTRE = np.array([20.0, 5.0])
RIM_R, RIM_Z = 7.0, 14.0


def _layer(points):
    """The soil layer of SfM ``points`` in this pot, looked for as the traits stage looks for it."""
    return pot_soil_layer(points, CENTRE, RIM_R, RIM_Z)


def _disc(rng, n, z, sigma=0.06, radius=0.75 * RIM_R):
    r, a = radius * np.sqrt(rng.uniform(0, 1, n)), rng.uniform(0, 2 * np.pi, n)
    return np.column_stack([CENTRE + np.column_stack([r * np.cos(a), r * np.sin(a)]), rng.normal(z, sigma, n)])


def _pot_scene(rng, soil_z, soil_points, leaves=400, leaf_top=None, under=12):
    """SfM points in a pot: the soil's patches, leaves and the crown spread above it up to ``leaf_top``, a few stray
    points under it, the rim's ring, and the room around."""
    parts = [_disc(rng, soil_points, soil_z)] if soil_points else []
    top = RIM_Z + 4.0 if leaf_top is None else leaf_top
    parts.append(np.column_stack([_disc(rng, leaves, 0.0)[:, :2], rng.uniform(soil_z + 0.4, top, leaves)]))
    parts.append(np.column_stack([_disc(rng, under, 0.0)[:, :2], rng.uniform(soil_z - 5.0, soil_z - 0.6, under)]))
    a = rng.uniform(0, 2 * np.pi, 300)
    parts.append(np.column_stack([CENTRE + RIM_R * np.column_stack([np.cos(a), np.sin(a)]), rng.uniform(0, RIM_Z, 300)]))
    parts.append(rng.uniform([-40, -40, 0], [60, 60, 60], (500, 3)))
    return np.concatenate(parts)


@pytest.mark.parametrize("seed", [0, 1])
def test_soil_seen_between_the_leaves(seed):
    rng = np.random.default_rng(seed)
    layer = _layer(_pot_scene(rng, 11.3, 120))
    assert layer is not None and layer.z == pytest.approx(11.3, abs=0.1)


def test_soil_hidden_under_leaves_but_for_a_few_patches():
    """A few dozen soil points under a canopy of leaves twice the pot's depth deep: still the lowest dense layer."""
    rng = np.random.default_rng(2)
    layer = _layer(_pot_scene(rng, 10.2, 35, leaves=500))
    assert layer is not None and layer.z == pytest.approx(10.2, abs=0.1)


def test_soil_found_under_leaves_far_denser_than_its_patches():
    """Foreign render 110 with its points triangulated again from every match: the leaves by the rim hold twice the
    points of the soil's few visible patches in a window. The soil is still the lowest layer, at its peak, whatever
    the leaves above it hold; a few stray points under it do not make a layer."""
    rng = np.random.default_rng(7)
    rim_leaves = np.column_stack([_disc(rng, 500, 0.0)[:, :2], rng.uniform(RIM_Z - 1.2, RIM_Z, 500)])
    pts = np.concatenate([_pot_scene(rng, 12.1, 60, leaves=150, under=8), rim_leaves])
    layer = _layer(pts)
    assert layer is not None and layer.z == pytest.approx(12.1, abs=0.1)


def test_soil_wholly_hidden_is_not_invented():
    """No soil point at all: what SfM sees lowest in the pot is the crown and the petioles' feet near the axis, a layer
    that does not fill the pot, so nothing comes out (the stage then falls back to the quick model's band or the rim's
    bound)."""
    rng = np.random.default_rng(3)
    crown = np.column_stack([_disc(rng, 200, 0.0, radius=0.25 * RIM_R)[:, :2], rng.uniform(10.0, 12.5, 200)])
    leaves = np.column_stack([_disc(rng, 300, 0.0, radius=RIM_R)[:, :2], rng.uniform(RIM_Z - 0.3, RIM_Z + 4.0, 300)])
    pts = np.concatenate([crown, leaves, rng.uniform([-40, -40, 0], [60, 60, 60], (500, 3))])
    assert _layer(pts) is None


def test_soil_seen_only_at_grazing_angles_is_not_a_layer():
    """Synthetic demo seed 732 (2026-11-30): a wide crown hides the soil from above; the frames that see it over the
    rim put a few points on it and more anywhere up to the rim, the crown's points near the axis among them, over the
    stray points under it. The windows climb that scatter to just under the rim (0.7 cm above the true soil there); a
    window holding fewer points than lie under it is no surface, so no layer comes out. The same scatter over a soil
    seen from above does not hide it."""
    rng = np.random.default_rng(9)
    soil_z = RIM_Z - 1.2
    under = np.column_stack([_disc(rng, 30, 0.0)[:, :2], rng.uniform(soil_z - 4.0, soil_z - 0.3, 30)])
    scatter = np.column_stack([_disc(rng, 45, 0.0)[:, :2], rng.uniform(soil_z, RIM_Z, 45)])
    crown = np.column_stack([_disc(rng, 12, 0.0, radius=0.3 * RIM_R)[:, :2], rng.uniform(soil_z, RIM_Z, 12)])
    room = rng.uniform([-40, -40, 0], [60, 60, 60], (500, 3))
    grazing = np.concatenate([_disc(rng, 12, soil_z, sigma=0.2), under, scatter, crown, room])
    assert _layer(grazing) is None
    layer = _layer(np.concatenate([grazing, _disc(rng, 80, soil_z)]))
    assert layer is not None and layer.z == pytest.approx(soil_z, abs=0.1)


def test_a_pot_filled_to_the_rim():
    rng = np.random.default_rng(4)
    layer = _layer(_pot_scene(rng, RIM_Z - 0.25, 150, leaves=250, under=5))
    assert layer is not None and layer.z == pytest.approx(RIM_Z - 0.25, abs=0.1)


def test_no_points_in_the_pot():
    rng = np.random.default_rng(5)
    assert _layer(rng.uniform([-40, -40, 0], [-20, -20, 60], (500, 3))) is None


def test_the_stage_takes_the_sfm_layer_over_the_quick_model_s_band(tmp_path):
    """Foreign render 110 (2026-11-27): the quick model drew the soil as a band from the rim down 1.5 cm, its middle
    1.1 cm above the true soil (height -5.9 % with exit 0); the SfM points in the pot lay on the soil. Without SfM
    points the band is used; without a pot there is no soil (a plant in the ground)."""
    rng = np.random.default_rng(6)
    ws = Workspace(tmp_path / "plant")
    pot = {"centre_cm": CENTRE.tolist(), "rim_radius_cm": RIM_R, "rim_z_cm": RIM_Z, "soil_z_cm": 13.5,
           "soil_bottom_z_cm": 12.0}
    ws.root.mkdir(parents=True)
    ws.segment_json.write_text(json.dumps({"capture": {"object": {"pot": pot}}}))
    assert workspace_soil(ws, calibrated=True)[:2] == (12.75, "the pot the segment stage found in 3D")
    pts = _pot_scene(rng, 11.2, 100)
    write_point_cloud(ws.sparse_points_ply, pts, np.zeros((len(pts), 3), np.uint8))
    z, source, disc, band = workspace_soil(ws, calibrated=True)
    assert z == pytest.approx(11.2, abs=0.1) and "SfM points" in source and disc is None and band == 0.0
    ws.segment_json.unlink()  # no pot recorded, and no cameras to look for one among the SfM points: in the ground
    assert workspace_soil(ws, calibrated=True)[:2] == (None, "no pot found: the height is the plant's extent (a plant "
                                                             "in the ground)")
    assert workspace_soil(ws, calibrated=False)[0] is None

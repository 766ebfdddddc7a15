"""Traits: cube found and measured by planes, clustering with floaters and a separated leaf, trait
values against the shared definitions, bad input, the CLI stage and the accuracy statistics."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from plantsplat import traitdefs
from plantsplat.cube import cube_surface_points
from plantsplat.traits.config import TraitsConfig
from plantsplat.traits.cube_fit import decide_up, fit_cube_planes
from plantsplat.traits.fruit import fruit_mask
from plantsplat.traits.measure import measure_traits
from plantsplat.traits.stats import accuracy_table, format_table, mae, mape, r2, rmse, scatter_plots

CUBE_FACES = ("+x", "-x", "+y", "-y", "top")  # the bottom face stands on the ground and is never seen


def _disc(rng, centre, normal, radius, n, ratio=0.6):
    """Points on an elliptic leaf blade (a flat ellipse) with a small random waviness."""
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    e1 = np.cross(normal, [0.0, 0.0, 1.0] if abs(normal[2]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    r = radius * np.sqrt(rng.random(n))
    a = rng.uniform(0, 2 * np.pi, n)
    u, v = r * np.cos(a), ratio * r * np.sin(a)
    w = 0.15 * np.sin(u) * np.cos(v)
    return centre + u[:, None] * e1 + v[:, None] * e2 + w[:, None] * normal


def _line(rng, a, b, n, jitter=0.05):
    t = rng.random(n)[:, None]
    return a + t * (np.asarray(b) - a) + rng.normal(0, jitter, (n, 3))


def make_plant_scene(seed=0, floaters=True, separated_leaf=True, noise=0.0, stretch=1.0):
    """A plant-like cloud (petioles, leaf blades, red fruit) on a 12 cm pot (pot not in the cloud),
    a noisy cube beside it, floaters, and one leaf whose petiole is missing. Its seven leaves spread evenly
    around the crown (a nearly round crown: the widths' axes are not fixed by it); ``stretch`` > 1 reaches the
    leaves that much farther along x (an elongated crown).

    Returns (points [N, 3], colors [N, 3] uint8, plant_mask [N] bool) in the calibrated frame (cm,
    z up, cube bottom centred on the origin).
    """
    rng = np.random.default_rng(seed)
    crown = np.array([24.0, 3.0, 12.0])
    parts, cols, is_plant = [], [], []

    def add(p, c, plant=True):
        parts.append(p)
        cols.append(np.broadcast_to(np.asarray(c, np.uint8), p.shape).copy())
        is_plant.append(np.full(len(p), plant))

    n_leaves = 7
    for i in range(n_leaves):
        az = 2 * np.pi * i / n_leaves + rng.uniform(-0.2, 0.2)
        el = np.radians(rng.uniform(35, 70))
        L = rng.uniform(9, 15) * (1.3 if i % 3 == 0 else 1.0)
        d = np.array([np.cos(az) * np.cos(el) * stretch, np.sin(az) * np.cos(el), np.sin(el)])
        L, d = L * np.linalg.norm(d), d / np.linalg.norm(d)
        blade_c = crown + d * L
        pet = _line(rng, crown, blade_c, 500)
        if separated_leaf and i == 3:
            # the middle of this petiole was not reconstructed: the leaf is a separate cluster
            t = (pet - crown) @ d / L
            pet = pet[(t < 0.6) | (t > 0.8)]
        add(pet, (70, 110, 40))
        add(_disc(rng, blade_c, [-d[0] * 0.3, -d[1] * 0.3, 1.0], rng.uniform(3.5, 5), 2500), (40, 95, 25))
    # fruit: red spheres on short peduncles, hanging from the crown
    for j in range(3):
        az = 2 * np.pi * j / 3 + rng.uniform(-0.5, 0.5)
        c = crown + [7 * np.cos(az), 7 * np.sin(az), -3.0 - j]
        add(_line(rng, crown, c, 150), (80, 120, 40))
        s = rng.normal(size=(500, 3))
        add(c + 1.1 * s / np.linalg.norm(s, axis=1, keepdims=True), (190, 15, 20))
    cube = cube_surface_points(10.0, 6000, rng, faces=CUBE_FACES)
    add(cube, (230, 230, 230), plant=False)
    if floaters:
        # isolated specks and one small blob away from everything
        lo, hi = np.array([-20.0, -30, -2]), np.array([60.0, 40, 45])
        specks = rng.uniform(lo, hi, (400, 3))
        plant_pts = np.concatenate([p for p, m in zip(parts, is_plant) if m[0]])
        from scipy.spatial import cKDTree

        d, _ = cKDTree(np.concatenate([plant_pts, cube])).query(specks)
        add(specks[d > 3.0][:60], (128, 128, 128), plant=False)
        add(rng.normal([60.0, -25, 20], 0.3, (25, 3)), (200, 30, 30), plant=False)
    pts = np.concatenate(parts)
    if noise:
        pts = pts + rng.normal(0, noise, pts.shape)
    return pts, np.concatenate(cols), np.concatenate(is_plant)


def _rel(a, b):
    return abs(a - b) / abs(b)


# --- cube -------------------------------------------------------------------------------------------


@pytest.mark.parametrize("noise_mm", [0.0, 1.0, 2.0])
def test_cube_edge_by_planes_within_1pct_on_noisy_clouds(noise_mm):
    rng = np.random.default_rng(int(noise_mm * 10))
    for trial in range(2):
        pts = cube_surface_points(10.0, 6000, rng, faces=CUBE_FACES, noise=noise_mm / 10)
        R = Rotation.random(random_state=trial + 7).as_matrix()
        scale = rng.uniform(0.05, 3.0)
        t = rng.uniform(-5, 5, 3)
        cloud = (pts @ R.T) * scale + t
        fit = fit_cube_planes(cloud)
        assert fit is not None
        assert _rel(fit.edge / scale, 10.0) < 0.01, (noise_mm, fit.edge / scale)
        decide_up(fit)
        assert fit.up_confident
        assert fit.up @ R[:, 2] > 0.999  # the unseen bottom face gives "up"
        # the bottom face's centre is the cube frame's origin
        np.testing.assert_allclose(fit.bottom_centre, t, atol=0.01 * 10.0 * scale)  # 1 % of the edge


def test_up_from_cameras_when_all_faces_are_seen():
    rng = np.random.default_rng(3)
    pts = cube_surface_points(10.0, 6000, rng)  # all six faces: coverage cannot tell up
    ang = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    cams = np.stack([40 * np.cos(ang), 40 * np.sin(ang), rng.uniform(5, 45, 24)], 1)
    R = Rotation.random(random_state=11).as_matrix()
    fit = decide_up(fit_cube_planes(pts @ R.T), camera_centres=cams @ R.T)
    assert fit.up_confident and fit.up @ R[:, 2] > 0.999


# --- clustering and traits ------------------------------------------------------------------------


def test_traits_equal_definitions_with_floaters_and_separated_leaf():
    pts, cols, plant = make_plant_scene(seed=1)
    truth = traitdefs.geometric_traits(pts[plant])
    res = measure_traits(pts, cols, calibrated=True)
    assert res.quality == "ok", res.reasons
    for k, v in truth.items():
        assert _rel(res.traits[k], v) < 0.01, (k, res.traits[k], v)
    assert len(res.plant_points) == int(plant.sum())  # the separated leaf joined, floaters and cube did not
    assert res.traits["fruit_count"] == 3
    assert abs(res.scale["aruco_vs_planes_pct"]) < 0.5
    assert res.clusters["cube_label"] is not None
    # robust values are trimmed, hence no larger
    for k in ("height_cm", "width1_cm", "width2_cm"):
        assert res.robust[k] <= res.traits[k] + 1e-9


def test_uncalibrated_cloud_scaled_and_levelled_by_the_cube():
    pts, cols, plant = make_plant_scene(seed=2, noise=0.05)
    truth = traitdefs.geometric_traits(pts[plant])
    R = Rotation.random(random_state=5).as_matrix()
    s = 0.0731  # arbitrary SfM units
    cloud = (pts @ R.T) * s + [3.0, -1.0, 2.0]
    res = measure_traits(cloud, cols, calibrated=False)
    assert res.quality == "ok", res.reasons
    assert res.scale["source"] == "cube_planes"
    assert _rel(res.scale["scale"], 1 / s) < 0.01
    for k in ("height_cm", "width1_cm", "width2_cm", "canopy_area_cm2"):
        assert _rel(res.traits[k], truth[k]) < 0.01, (k, res.traits[k], truth[k])
    assert _rel(res.traits["canopy_volume_cm3"], truth["canopy_volume_cm3"]) < 0.03


def test_gaussian_cube_measured_by_its_envelope_not_its_sunken_planes():
    """A splat's faces are drawn by the outer layer of Gaussians that fill up to ~1 cm inside them:
    plane fits through the face Gaussians sink inside, the envelope does not. With opacities (a
    Gaussian export) the cube is measured by its envelope and the right ArUco scale passes."""
    pts, cols, plant = make_plant_scene(seed=5, floaters=False)
    rng = np.random.default_rng(5)
    cube = np.flatnonzero(~plant)  # the cube's surface points (the scene has no floaters)
    # push each cube point inside along its face's inward normal by 0..0.8 cm; keep 5 % on the surface
    local = pts[cube] - [0.0, 0.0, 5.0]  # cube centre at the origin
    ax = np.abs(local).argmax(1)
    depth = np.where(rng.random(len(cube)) < 0.05, 0.0, rng.uniform(0.0, 0.8, len(cube)))
    inward = -np.sign(local[np.arange(len(cube)), ax])
    pts = pts.copy()
    pts[cube, ax] += inward * depth
    res = measure_traits(pts, cols, calibrated=True, opacity=np.ones(len(pts)))
    assert res.scale["cube_edge_method"] == "envelope"
    assert abs(res.scale["aruco_vs_cube_pct"]) < 1.0, res.scale
    assert res.scale["cube_edge_cm_planes"] < 9.6  # the planes sank inside
    assert not any("ArUco" in r for r in res.reasons), res.reasons
    assert abs(res.scale["cube_bottom_z_cm"]) < 0.2  # 2 % of the edge
    planes = measure_traits(pts, cols, calibrated=True, opacity=np.ones(len(pts)),
                            settings=TraitsConfig(cube_edge="planes"))
    assert planes.scale["cube_edge_method"] == "planes" and any("ArUco" in r for r in planes.reasons)
    # without opacities or extent samples (any point cloud) 'auto' fits planes
    assert measure_traits(pts, cols, calibrated=True).scale["cube_edge_method"] == "planes"


def test_cube_axes_compared_between_seen_faces_only():
    """The cube's axes are compared where both opposite faces are seen: the vertical extent (the bottom face on
    the ground, Gaussians reaching out from the top face only) is not comparable and is left out; a cube stretched
    along one horizontal axis is still caught."""
    from plantsplat.traits.cube_fit import use_envelope

    rng = np.random.default_rng(3)
    pts = cube_surface_points(10.0, 9000, rng, faces=CUBE_FACES)
    reach = rng.normal(0.0, 0.1, pts.shape)  # the Gaussians' extents reach out on every side...
    reach[:, 2] = np.where(pts[:, 2] > 9.99, np.abs(reach[:, 2]), 0.0)  # ...but not below the ground
    cloud = pts + reach
    cloud[pts[:, 2] > 9.99, 2] -= 0.3  # the top face drawn 3 mm low, as on the demo
    fit = use_envelope(fit_cube_planes(cloud, size_hint=10.0), cloud)
    vertical = int(np.argmax(np.abs(fit.axes[:, 2])))
    assert fit.extra["edge_per_axis_planes"][vertical] is None
    horizontal = [e for i, e in enumerate(fit.edge_per_axis) if i != vertical]
    assert (max(horizontal) - fit.edge_per_axis[vertical]) / fit.edge > 0.03  # the old three-axis check fired
    assert fit.axis_spread() < 0.01
    stretched = cloud * [1.06, 1.0, 1.0]
    fit = use_envelope(fit_cube_planes(stretched, size_hint=10.0), stretched)
    assert fit.axis_spread() == pytest.approx(0.058, abs=0.01)


def test_scale_disagreement_is_reported_and_flagged():
    pts, cols, _ = make_plant_scene(seed=4, floaters=False)
    res = measure_traits(pts * 1.06, cols, calibrated=True)  # a 6 % wrong ArUco scale
    assert res.quality == "warning"
    assert res.scale["aruco_vs_planes_pct"] == pytest.approx(6.0, abs=0.5)
    assert any("ArUco" in r for r in res.reasons)


def test_fruit_colour_model():
    s = TraitsConfig()
    cols = np.array([[190, 15, 20], [160, 8, 30], [129, 59, 26], [40, 95, 25], [240, 240, 230], [30, 3, 3]], np.uint8)
    assert fruit_mask(cols, s).tolist() == [True, True, False, False, False, False]


# --- bad input -------------------------------------------------------------------------------------


def test_empty_cloud_fails_clearly():
    res = measure_traits(np.zeros((0, 3)), None, calibrated=True)
    assert res.quality == "failed" and all(res.traits[k] is None for k in traitdefs.TRAIT_KEYS)
    res = measure_traits(np.full((500, 3), np.nan), None, calibrated=True)
    assert res.quality == "failed"


def test_uncalibrated_without_cube_gives_no_numbers():
    pts, cols, plant = make_plant_scene(seed=5, floaters=False)
    res = measure_traits(pts[plant] * 0.1, cols[plant], calibrated=False)
    assert res.quality == "failed"
    assert res.traits["height_cm"] is None
    assert "no cube" in res.reasons[0]


def test_plant_in_many_pieces_is_flagged_with_a_merge_distance():
    rng = np.random.default_rng(6)
    cube = cube_surface_points(10.0, 5000, rng, faces=CUBE_FACES)
    blobs = [rng.normal([25 + 12 * (i % 4), 12 * (i // 4), 15], 0.8, (600, 3)) for i in range(16)]
    res = measure_traits(np.concatenate([cube, *blobs]), None, calibrated=True,
                         settings=TraitsConfig(merge_distance_cm=4.0))
    assert res.quality == "warning"
    assert any("fragmented" in r or "left out" in r for r in res.reasons), res.reasons


def test_leaves_apart_from_the_crown_are_plant_and_floaters_are_not():
    """By default every cluster but the cube, floaters and what lies under the ground is plant: leaves on
    petioles too thin to reconstruct stand 12 cm apart and all count."""
    rng = np.random.default_rng(6)
    cube = cube_surface_points(10.0, 5000, rng, faces=CUBE_FACES)
    blobs = [rng.normal([25 + 12 * (i % 4), 12 * (i // 4), 15], 0.8, (600, 3)) for i in range(16)]
    floater = rng.normal([60, 60, 30], 0.3, (8, 3))  # too few points for a cluster of its own
    res = measure_traits(np.concatenate([cube, *blobs, floater]), None, calibrated=True)
    assert len(res.plant_points) >= 0.99 * 16 * 600  # all 16 (less DBSCAN's few outliers)
    assert res.plant_points[:, 1].max() < 45  # not the floater
    assert 51 < res.traits["width1_cm"] < 56  # the 4 x 4 grid's diagonal (36 x 36 cm) plus the blobs
    assert not any("fragmented" in r for r in res.reasons)


def test_no_cube_in_calibrated_cloud_is_flagged_not_fatal():
    pts, cols, plant = make_plant_scene(seed=7, floaters=False)
    res = measure_traits(pts[plant], cols[plant], calibrated=True)
    assert res.quality == "warning"
    assert any("no cube" in r for r in res.reasons)
    assert _rel(res.traits["height_cm"], traitdefs.plant_height(pts[plant])) < 0.01


# --- accuracy statistics ---------------------------------------------------------------------------


def test_statistics_match_the_paper_definitions():
    rng = np.random.default_rng(0)
    y = rng.uniform(10, 40, 15)
    yh = y * rng.normal(1, 0.05, 15) + rng.normal(0, 0.5, 15)
    # independent loop implementations of the paper's equations
    n = len(y)
    ybar = sum(y) / n
    ss_res = sum((a - b) ** 2 for a, b in zip(y, yh))
    ss_tot = sum((a - ybar) ** 2 for a in y)
    assert r2(y, yh) == pytest.approx(1 - ss_res / ss_tot)
    assert rmse(y, yh) == pytest.approx((ss_res / n) ** 0.5)
    assert mape(y, yh) == pytest.approx(100 / n * sum(abs((a - b) / a) for a, b in zip(y, yh)))
    assert mae(y, yh) == pytest.approx(sum(abs(a - b) for a, b in zip(y, yh)) / n)
    t = accuracy_table({"height_cm": yh}, {"height_cm": y}, ["height_cm"])["height_cm"]
    assert t["acc"] == pytest.approx(100 - t["mape"])
    assert r2([1, 2, 3], [3, 2, 1]) == pytest.approx(-3.0)  # worse than the mean: negative
    with pytest.raises(ValueError):
        mape([0.0, 1.0], [0.1, 1.0])
    assert "| height from the soil (cm) |" in format_table({"height_cm": t})


def test_scatter_plot_png(tmp_path):
    est = {f"p{i}": {"height_cm": 10.0 + i + 0.3 * (-1) ** i, "width1_cm": 20.0 + i} for i in range(6)}
    gt = {f"p{i}": {"height_cm": 10.0 + i, "width1_cm": 20.5 + i} for i in range(6)}
    out = tmp_path / "scatter.png"
    scatter_plots(est, gt, ["height_cm", "width1_cm"], out)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    table = accuracy_table(est, gt, ["width1_cm"])
    assert table["width1_cm"]["mae"] == pytest.approx(0.5)


# --- the CLI stage ----------------------------------------------------------------------------------


def _write_points_ply(path, pts, cols, opacity):
    from plyfile import PlyData, PlyElement

    arr = np.empty(len(pts), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"),
                                    ("blue", "u1"), ("opacity", "f4"), ("scale_0", "f4"), ("scale_1", "f4"),
                                    ("scale_2", "f4")])
    arr["x"], arr["y"], arr["z"] = pts.T
    arr["red"], arr["green"], arr["blue"] = cols.T
    arr["opacity"] = opacity
    for i in range(3):
        arr[f"scale_{i}"] = 0.1
    path.parent.mkdir(parents=True, exist_ok=True)
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(path))


def test_traits_command_writes_json_csv_png(tmp_path, capsys):
    from plantsplat.cli import main

    pts, cols, plant = make_plant_scene(seed=8)
    # low-opacity Gaussians far away must be filtered out by the opacity threshold
    junk = np.random.default_rng(0).uniform(100, 200, (300, 3))
    ws = tmp_path / "plant_01"
    _write_points_ply(ws / "export" / "points.ply", np.concatenate([pts, junk]),
                      np.concatenate([cols, np.full((300, 3), 9, np.uint8)]),
                      np.r_[np.full(len(pts), 0.9), np.full(300, 0.02)])
    (ws / "poses.json").write_text(json.dumps({"scale_source": "aruco", "scale_uncertainty": {"relative_se": 0.0021}}))
    assert main(["traits", str(ws)]) == 0
    out = json.loads((ws / "traits.json").read_text())
    for k in traitdefs.TRAIT_KEYS:
        assert k in out
    assert out["quality"] == "ok" and out["scale_source"] == "aruco"
    assert out["scale"]["standard_error_pct"] == pytest.approx(0.21)  # the poses stage's, carried
    assert _rel(out["height_cm"], traitdefs.plant_height(pts[plant])) < 0.01
    lines = (ws / "traits.csv").read_text().strip().splitlines()
    assert len(lines) == 2 and lines[0].startswith("plant,height_cm")
    assert (ws / "traits.png").read_bytes()[:4] == b"\x89PNG"


def test_traits_measure_with_the_cube_the_poses_stage_recorded(tmp_path):
    """Issue 42 #1: a 20 cm cube (`--poses.cube-size 20 --poses.marker-size 19.2`) is recorded by the poses stage
    in markers.json; the traits stage finds that cube (not "not a cube", measured as plant) and its checks use it."""
    from plantsplat.cli import main

    pts, cols, plant = make_plant_scene(seed=8, floaters=False)
    big = pts * 2.0  # the same scene twice as large: a 20 cm cube beside a plant twice the size
    ws = tmp_path / "plant_20cm"
    _write_points_ply(ws / "export" / "points.ply", big, cols, np.full(len(pts), 0.9))
    (ws / "poses.json").write_text(json.dumps({"scale_source": "aruco"}))
    (ws / "markers.json").write_text(json.dumps({"cube": {"size": 20.0, "marker_size": 19.2,
                                                          "dictionary": "DICT_4X4_50", "face_ids": list(range(6))}}))
    assert main(["traits", str(ws), "--extent-sigma", "0", "--no-figure"]) == 0
    out = json.loads((ws / "traits.json").read_text())
    w1, w2 = traitdefs.pca_widths(big[plant])
    assert out["cube"] is not None and out["scale"]["cube_edge_cm"] == pytest.approx(20.0, rel=0.03)
    assert _rel(out["width1_cm"], w1) < 0.03 and _rel(out["width2_cm"], w2) < 0.03
    height_check = next(c for c in out["checks"] if c["name"] == "plant_height_cm")
    assert height_check["threshold"] == pytest.approx(0.3 * 20.0)


def test_traits_command_bad_input_one_line_error(tmp_path, capsys):
    from plantsplat.cli import main

    ws = tmp_path / "ws"
    ws.mkdir()
    assert main(["traits", str(ws)]) == 1  # no export yet
    err = capsys.readouterr().err
    assert "splat.ply" in err and "plantsplat export" in err and "Traceback" not in err
    # an unscaled cloud without a cube: failed traits.json, the failed result's exit code, no numbers
    pts, cols, plant = make_plant_scene(seed=9, floaters=False)
    _write_points_ply(ws / "export" / "points.ply", pts[plant] * 0.2, cols[plant], np.ones(int(plant.sum())))
    (ws / "poses.json").write_text(json.dumps({"scale_source": "none"}))
    assert main(["traits", str(ws)]) == 4
    out = json.loads((ws / "traits.json").read_text())
    assert out["quality"] == "failed" and out["height_cm"] is None
    assert "no cube" in " ".join(capsys.readouterr().err.split())  # the log wraps long lines
    (ws / "export" / "points.ply").write_bytes(b"ply\ngarbage")
    assert main(["traits", str(ws)]) == 1
    assert "not a readable PLY" in capsys.readouterr().err


def test_extent_sampling_from_splat_ply(tmp_path):
    """--extent-sigma: Gaussians' axis ends count. Each plant point becomes a flat Gaussian whose
    largest axis is along z with sigma 0.25 cm, so the height grows by 2 * k_sigma * 0.25 cm. At 0 the
    centres alone count, and the PLY's opacity is still read as a logit (the plant's -1 is 0.27, kept)."""
    from plantsplat.cli import main
    from plantsplat.ply import write_splat as write_splat_ply

    pts, cols, plant = make_plant_scene(seed=10, floaters=False, stretch=1.5)
    keep = np.arange(len(pts)) % 3 == 0  # 7 points per Gaussian: keep the cloud small
    pts, cols, plant = pts[keep], cols[keep], plant[keep]
    n = len(pts)
    sig = np.where(plant[:, None], [[0.01, 0.01, 0.25]], [[0.01, 0.01, 0.01]])  # [N, 3]
    sh0 = ((cols / 255.0) - 0.5) / 0.28209479177387814
    ws = tmp_path / "ws"
    write_splat_ply(ws / "export" / "splat.ply", pts, np.log(sig), np.tile([1.0, 0, 0, 0], (n, 1)),
                    np.where(plant, -1.0, 4.0), sh0[:, None, :], np.zeros((n, 0, 3)))
    (ws / "poses.json").write_text(json.dumps({"scale_source": "aruco"}))
    assert main(["traits", str(ws), "--extent-sigma", "2", "--no-figure"]) == 0
    out = json.loads((ws / "traits.json").read_text())
    h0 = traitdefs.plant_height(pts[plant])
    assert out["height_cm"] == pytest.approx(h0 + 1.0, rel=0.01)
    assert out["quality"] == "ok", out["quality_reasons"]
    assert out["fruit_count"] == 3  # colours from the SH DC term
    assert main(["traits", str(ws), "--points", str(ws / "export" / "splat.ply"), "--extent-sigma", "0",
                 "--no-figure"]) == 0
    out = json.loads((ws / "traits.json").read_text())
    assert out["height_cm"] == pytest.approx(h0, rel=0.01)
    assert out["quality"] == "ok", out["quality_reasons"]


def test_the_plant_alone_is_written_as_a_splat_of_its_own(tmp_path):
    """plant.ply: the splat's rows whose Gaussians the measurement put on the plant, every column as it was; not the
    cube, the floaters or the Gaussians below the opacity threshold. A measurement without plant Gaussians (a plain
    point cloud) removes it."""
    from plantsplat.cli import main
    from plantsplat.ply import read_splat, read_vertices
    from plantsplat.ply import write_splat as write_splat_ply

    pts, cols, plant = make_plant_scene(seed=14, floaters=True)
    keep = np.arange(len(pts)) % 3 == 0
    pts, cols, plant = pts[keep], cols[keep], plant[keep]
    n = len(pts)
    faint = plant & (np.arange(n) % 50 == 0)  # plant Gaussians below the opacity threshold
    sh0 = ((cols / 255.0) - 0.5) / 0.28209479177387814
    ws = tmp_path / "ws"
    splat = ws / "export" / "splat.ply"
    write_splat_ply(splat, pts, np.log(np.full((n, 3), 0.05)), np.tile([1.0, 0, 0, 0], (n, 1)),
                    np.where(faint, -4.0, 4.0), sh0[:, None, :], np.zeros((n, 3, 3)))
    (ws / "poses.json").write_text(json.dumps({"scale_source": "aruco"}))
    assert main(["traits", str(ws), "--no-figure"]) == 0
    out = read_splat(ws / "plant.ply")
    assert read_vertices(ws / "plant.ply").dtype == read_vertices(splat).dtype  # every column, as in the splat
    rows = {tuple(p) for p in np.asarray(pts, np.float32)}
    got = {tuple(p) for p in out["means"]}
    wanted = {tuple(p) for p in np.asarray(pts[plant & ~faint], np.float32)}
    assert got <= rows and got <= wanted  # no cube, floater or faint Gaussian
    assert len(got) >= 0.98 * len(wanted)
    assert len(out["means"]) == len(got)  # each Gaussian once
    assert np.all(out["opacities"] == 4.0) and out["shN"].shape == (len(got), 3, 3)
    cloud = ws / "points.ply"
    _write_points_ply(cloud, pts, cols, np.ones(n))
    assert main(["traits", str(ws), "--points", str(cloud), "--no-figure"]) == 0
    assert not (ws / "plant.ply").exists()


def test_traits_command_unscaled_workspace_uses_cube_and_cameras(tmp_path):
    from plantsplat.cli import main

    pts, cols, plant = make_plant_scene(seed=12, floaters=False)
    R = Rotation.random(random_state=2).as_matrix()
    s, t = 0.21, np.array([1.0, 2.0, -3.0])
    ang = np.linspace(0, 2 * np.pi, 30, endpoint=False)
    cams = np.stack([25 + 45 * np.cos(ang), 45 * np.sin(ang), np.full(30, 30.0)], 1)  # around the plant
    frames = []
    for c in cams @ R.T * s + t:
        m = np.eye(4)
        m[:3, 3] = c
        frames.append({"file_path": "images/x.png", "transform_matrix": m.tolist()})
    ws = tmp_path / "ws"
    _write_points_ply(ws / "export" / "points.ply", (pts @ R.T) * s + t, cols, np.ones(len(pts)))
    (ws / "poses.json").write_text(json.dumps({"scale_source": "none"}))
    (ws / "transforms.json").write_text(json.dumps({"frames": frames}))
    assert main(["traits", str(ws), "--no-figure"]) == 0
    out = json.loads((ws / "traits.json").read_text())
    # points.ply carries opacities: a Gaussian export, so the cube is measured by its envelope
    assert out["scale_source"] == "cube_envelope" and out["quality"] == "ok", out["quality_reasons"]
    assert out["scale"]["up_method"].startswith("cameras")
    assert _rel(out["width1_cm"], traitdefs.pca_widths(pts[plant])[0]) < 0.01
    assert _rel(out["height_cm"], traitdefs.plant_height(pts[plant])) < 0.01


def test_large_clouds_clustered_on_a_subset_give_the_same_plant():
    pts, cols, plant = make_plant_scene(seed=1)
    res = measure_traits(pts, cols, calibrated=True, settings=TraitsConfig(max_cluster_points=6000))
    assert res.quality == "ok", res.reasons
    assert len(res.plant_points) == int(plant.sum())
    assert res.traits["height_cm"] == pytest.approx(traitdefs.plant_height(pts[plant]), rel=1e-9)


LINKED = TraitsConfig(merge_distance_cm=4.0)  # clouds made without 3D masks: clusters join by their gaps


def test_hanging_fruit_without_peduncles_join_the_plant():
    """Fruit whose peduncles were not reconstructed hang as separate red clusters: they join the plant when
    they are within reach and below its top; red things far away or above the plant, and green clusters at
    the same distance, do not."""
    rng = np.random.default_rng(3)
    pts, cols, plant = make_plant_scene(seed=2, floaters=False, separated_leaf=False)
    keep = ~((cols[:, 0] == 80) & (cols[:, 1] == 120))  # drop the peduncles
    pts, cols, plant = pts[keep], cols[keep], plant[keep]
    body = pts[plant]
    crown = np.array([24.0, 3.0, 12.0])  # make_plant_scene's crown; its fruit hang 7 cm out, 3-5 cm lower

    def blob(c, colour, n=400):
        s = rng.normal(size=(n, 3))
        return c + 1.2 * s / np.linalg.norm(s, axis=1, keepdims=True), np.tile(np.array(colour, np.uint8), (n, 1))

    hang, hang_c = blob(crown + [2.5, 0.0, -8.0], (200, 20, 30))  # under the crown, 5-8 cm from the other fruit
    far, far_c = blob(crown + [45.0, 0.0, 0.0], (200, 20, 30))  # a red object across the room
    high, high_c = blob(crown + [0.0, 0.0, body[:, 2].max() - crown[2] + 6.0], (200, 20, 30))  # above the plant
    green, green_c = blob(crown + [-2.5, 0.0, -8.0], (40, 120, 40))  # a green blob there (not fruit)
    from scipy.spatial import cKDTree

    d_hang = cKDTree(body).query(hang)[0].min()
    assert 4.0 < d_hang < 15.0  # beyond the usual merge distance, within fruit reach
    P = np.concatenate([pts, hang, far, high, green])
    C = np.concatenate([cols, hang_c, far_c, high_c, green_c])
    res = measure_traits(P, C, calibrated=True, settings=LINKED)
    got = res.plant_points
    near = lambda b: np.isin(got.view([("", got.dtype)] * 3), b.view([("", b.dtype)] * 3)).any()  # noqa: E731
    assert near(hang) and not near(far) and not near(high) and not near(green)
    assert res.traits["fruit_count"] == 4  # the three around the crown and the one under it
    assert res.traits["height_cm"] > body[:, 2].max() - body[:, 2].min() + 2.0  # the hanging fruit counts for height
    assert any("fruit-coloured" in n for n in res.notes)
    # switched off: without their peduncles all fruit stay out (they hang more than 4 cm from the leaves)
    off = measure_traits(P, C, calibrated=True, settings=TraitsConfig(merge_distance_cm=4.0, fruit_join_cm=0))
    assert off.traits["fruit_count"] == 0


def test_hanging_unripe_fruit_join_the_plant_but_pale_objects_do_not():
    """Unripe (cream to pale yellow-green) fruit on unreconstructed peduncles join like red ones, and so does a truss
    of a ripe and an unripe fruit hanging side by side; a pale piece wider than a fruit (a beige box or wall) at the
    same distance does not, and the plant's quality warns only about the large clusters still left out."""
    rng = np.random.default_rng(4)
    pts, cols, plant = make_plant_scene(seed=2, floaters=False, separated_leaf=False)
    keep = ~((cols[:, 0] == 80) & (cols[:, 1] == 120))  # drop the peduncles: the scene's fruit hang apart
    pts, cols, plant = pts[keep], cols[keep], plant[keep]
    crown = np.array([24.0, 3.0, 12.0])
    s = rng.normal(size=(600, 3))
    unripe = crown + [2.5, 0.0, -8.0] + 1.3 * s / np.linalg.norm(s, axis=1, keepdims=True)  # 2.6 cm across
    box = crown + [0.0, -14.0, -8.0] + rng.uniform([-5, -0.3, -4.5], [5, 0.3, 4.5], (3000, 3))  # 10 x 9 cm, same colour
    s = rng.normal(size=(800, 3))
    truss = crown + [14.0, 0.0, -5.5] + 1.3 * s / np.linalg.norm(s, axis=1, keepdims=True)
    truss[400:, 2] -= 2.6  # two fruit one above the other, touching: 5.2 cm long, 2.6 cm thick
    from scipy.spatial import cKDTree

    for b in (unripe, box, truss):
        assert 4.0 < cKDTree(pts[plant]).query(b)[0].min() < 15.0  # beyond the merge distance, within reach
    cream = lambda n: np.tile(np.array([200, 205, 150], np.uint8), (n, 1))  # noqa: E731
    # 3/8 red, 3/8 unripe, the rest ripening orange: neither colour alone makes half of it
    truss_c = np.concatenate([np.tile(np.array([200, 20, 30], np.uint8), (300, 1)), cream(300),
                              np.tile(np.array([190, 100, 40], np.uint8), (200, 1))])
    P = np.concatenate([pts, unripe, box, truss])
    C = np.concatenate([cols, cream(len(unripe)), cream(len(box)), truss_c])
    res = measure_traits(P, C, calibrated=True, settings=LINKED)
    got = {tuple(p) for p in res.plant_points.round(6)}
    assert all(tuple(p) in got for p in unripe.round(6)), "unripe"
    assert all(tuple(p) in got for p in truss.round(6)), "truss"
    assert not any(tuple(p) in got for p in box.round(6))
    assert [r for r in res.reasons if "too far" in r] == [f"1 large cluster(s) left out as too far from the plant "
                                                          f"({len(box)} points): check the plant is not split"]
    alone = measure_traits(np.concatenate([pts, unripe]), np.concatenate([cols, cream(len(unripe))]), calibrated=True,
                           settings=LINKED)
    assert alone.quality == "ok", alone.reasons  # every far cluster joined: nothing to warn about
    off = measure_traits(P, C, calibrated=True, settings=TraitsConfig(merge_distance_cm=4.0, fruit_join_unripe_cm=0))
    got_off = {tuple(p) for p in off.plant_points.round(6)}
    assert not any(tuple(p) in got_off for p in unripe.round(6))


def test_nothing_under_the_ground_or_in_the_cube_is_plant():
    """Issue 40 (foreign render 101, 2026-11-27): a blob of Gaussians wholly below the ground, the ends of the
    cube's Gaussians reaching out of its box, and pieces of its faces drawn just outside it were measured as plant
    (width 2 +38-42 %). None of them is plant."""
    from plantsplat.ply import gaussian_extent_points

    pts, cols, plant = make_plant_scene(seed=5, floaters=False)
    rng = np.random.default_rng(5)
    under = rng.uniform([-10.0, -2.0, -1.4], [-8.0, 0.0, -0.2], (300, 3))  # beside the cube, below the ground
    edge = np.stack([np.full(120, -4.9), np.linspace(-4.0, 4.0, 120), np.full(120, 0.2)], 1)  # the cube's bottom edge
    face = rng.uniform([-6.9, 1.3, 3.0], [-5.8, 2.6, 4.5], (300, 3))  # a piece of a face, drawn outside the box
    centres = np.concatenate([pts, under, edge, face])
    scales = np.full((len(centres), 3), 0.02)
    scales[len(pts) + len(under):-len(face), 0] = 1.5  # long Gaussians across the edge: ends 3 cm out of the box
    cloud = gaussian_extent_points(centres, scales, np.tile([1.0, 0, 0, 0], (len(centres), 1)), 2.0)
    colours = np.tile(np.concatenate([cols, np.full((len(under) + len(edge) + len(face), 3), 90, np.uint8)]), (7, 1))
    centre = np.zeros(len(cloud), bool)
    centre[: len(centres)] = True
    res = measure_traits(cloud, colours, calibrated=True, centre_mask=centre)
    assert res.plant_points[:, 2].min() >= pts[plant, 2].min() - 0.2
    assert res.plant_points[:, 0].min() >= pts[plant, 0].min() - 0.2
    assert res.traits["width2_cm"] == pytest.approx(measure_traits(pts, cols, calibrated=True).traits["width2_cm"],
                                                    rel=0.03)


def test_a_piece_of_the_plant_on_the_cube_s_side_is_plant_and_a_piece_of_a_face_is_not():
    """Synthetic demo seed 404 (2026-11-27): fruit and leaves hanging over the pot's rim on the cube's side, 8-9 cm from
    the cube, were nearer it than the plant's upper body and left out as pieces of the cube (height extent -11 %,
    volume -20 %). A piece of the cube lies on its faces; what hangs centimetres out is the plant's."""
    pts, cols, plant = make_plant_scene(seed=6, floaters=False, separated_leaf=False)
    rng = np.random.default_rng(6)
    s = rng.normal(size=(600, 3))
    fruit = np.array([13.0, 3.0, 5.0]) + 1.2 * s / np.linalg.norm(s, axis=1, keepdims=True)  # 8 cm from the cube's +x face
    face = rng.uniform([5.6, -2.0, 3.0], [6.4, -0.5, 4.5], (300, 3))  # a piece of that face, drawn 1 cm outside it
    body = pts[plant]
    to_box = 13.0 - 1.2 - 5.0
    assert np.min(np.linalg.norm(body - fruit.mean(axis=0), axis=1)) > to_box  # nearer the cube than the plant
    P = np.concatenate([pts, fruit, face])
    C = np.concatenate([cols, np.tile(np.array([200, 20, 30], np.uint8), (len(fruit), 1)),
                        np.full((len(face), 3), 230, np.uint8)])
    res = measure_traits(P, C, calibrated=True)
    got = {tuple(p) for p in res.plant_points.round(6)}
    assert all(tuple(p) in got for p in fruit.round(6))
    assert not any(tuple(p) in got for p in face.round(6))
    assert res.traits["height_extent_cm"] == pytest.approx(body[:, 2].max() - fruit[:, 2].min(), abs=0.05)


def test_height_is_measured_from_the_soil():
    """A ruler on the soil: fruit hanging over the rim do not change the height; the paper's extent is kept."""
    pts, cols, plant = make_plant_scene(seed=3, floaters=False)
    soil = 11.0  # the crown sits at 12 cm, fruit hang down to 8 cm
    res = measure_traits(pts, cols, calibrated=True, soil_z=soil)
    top = pts[plant, 2].max()
    assert res.traits["height_cm"] == pytest.approx(top - soil, abs=1e-9)
    assert res.traits["height_extent_cm"] == pytest.approx(top - pts[plant, 2].min(), abs=1e-9)
    assert res.traits["height_extent_cm"] > res.traits["height_cm"]
    assert res.to_json()["soil_z_cm"] == soil
    alone = measure_traits(pts, cols, calibrated=True)  # no soil known: the extent
    assert alone.traits["height_cm"] == pytest.approx(alone.traits["height_extent_cm"])


def _measured_workspace(tmp_path, pts, cols, segment_confidence: list[float] | None = None, pot_soil: float | None = None,
                        pot: dict | None = None):
    ws = tmp_path / "plant"
    _write_points_ply(ws / "export" / "points.ply", pts, cols, np.ones(len(pts)))
    (ws / "poses.json").write_text(json.dumps({"scale_source": "aruco"}))
    if segment_confidence is not None:
        frames = [{"name": f"frame_{i:05d}.png", "confidence": c} for i, c in enumerate(segment_confidence)]
        obj = {"pot": pot or {"soil_z_cm": pot_soil}} if pot_soil is not None or pot else {}
        (ws / "segment.json").write_text(json.dumps({"frames": frames, "capture": {"object": obj}}))
    return ws


def test_a_result_failing_its_checks_is_written_marked_and_exits_4(tmp_path, capsys):
    from plantsplat.cli import main

    pts, cols, _ = make_plant_scene(seed=4, floaters=False, stretch=1.5)
    ws = _measured_workspace(tmp_path, pts, cols, [0.9] * 20, pot_soil=11.0)
    assert main(["traits", str(ws), "--no-figure"]) == 0
    good = json.loads((ws / "traits.json").read_text())
    assert good["quality"] == "ok" and good["soil_source"].startswith("the pot the segment stage found")
    assert {c["name"] for c in good["checks"]} >= {"masks_confidence_mean", "masks_unsure_share", "plant_points"}
    # masks the segmenter was unsure of in most frames: the numbers come out, but marked failed
    ws = _measured_workspace(tmp_path / "unsure", pts, cols, [0.9] * 5 + [0.3] * 15)
    assert main(["traits", str(ws), "--no-figure"]) == 4
    out = json.loads((ws / "traits.json").read_text())
    assert out["quality"] == "failed" and out["height_cm"] is not None
    assert any(r.startswith("check masks_unsure_share") for r in out["quality_reasons"])
    assert "failed" in (ws / "traits.csv").read_text()
    assert "FAILED" in capsys.readouterr().err


def test_the_figure_shows_the_verdict_of_the_checks(tmp_path, monkeypatch):
    """traits.png printed the measurement's own `ok` above a result its checks had marked failed."""
    import matplotlib.figure

    from plantsplat.cli import main

    titles = []
    real = matplotlib.figure.Figure.suptitle
    monkeypatch.setattr(matplotlib.figure.Figure, "suptitle", lambda fig, t, **kw: titles.append(t) or real(fig, t, **kw))
    pts, cols, _ = make_plant_scene(seed=4, floaters=False, stretch=1.5)
    ws = _measured_workspace(tmp_path, pts, cols, [0.9] * 5 + [0.3] * 15)
    assert main(["traits", str(ws)]) == 4
    assert json.loads((ws / "traits.json").read_text())["quality"] == "failed"
    assert len(titles) == 1 and "quality: failed" in titles[0]


def test_the_height_is_judged_by_bounds_found_apart_from_it(tmp_path):
    """Issue 41. Soil seen in the pot: bounds within 5 %, ok. Soil hidden under the leaves (the rim stands for it):
    the plant's lowest point in the pot and the ground bound it; the height is measured from that point, the truth
    inside the bounds, and failed: the bounds are too wide to stand behind (before, a check passed on the point the
    same code had set); a plant that does not reach into the pot also lost its base (the lower petioles missing).
    No pot (a plant in the ground): the extent, ok."""
    from plantsplat.traits.stage import run as traits_workspace

    pts, cols, plant = make_plant_scene(seed=4, floaters=False, stretch=1.5)
    P = pts[plant]
    crown, low, top = P[np.argmin(P[:, 2])], float(P[:, 2].min()), float(P[:, 2].max())
    rim = {"centre_cm": crown[:2].tolist(), "rim_radius_cm": 8.0, "rim_z_cm": low + 1.0}
    seen = traits_workspace(_measured_workspace(tmp_path / "seen", pts, cols, [0.9] * 20,
                                                pot={**rim, "soil_z_cm": low - 0.5}), figure=False)
    assert seen["quality"] == "ok" and seen["soil_interval_cm"] == pytest.approx([low - 0.75, low - 0.25], abs=1e-3)
    lo, hi = seen["height_bounds_cm"]
    assert lo < top - (low - 0.5) < hi and (hi - lo) / seen["height_cm"] < 0.05
    soil = low - 3.0  # the truth: 3 cm below the plant's lowest point, under the leaves
    hidden = traits_workspace(_measured_workspace(tmp_path / "hidden", pts, cols, [0.9] * 20,
                                                  pot={**rim, "soil_z_cm": rim["rim_z_cm"]}), figure=False)
    failed = {c["name"] for c in hidden["checks"] if not c["passed"]}
    assert hidden["quality"] == "failed" and failed == {"height_interval_share", "height_interval_share_warn"}
    assert hidden["soil_interval_cm"] == pytest.approx([0.0, low], abs=1e-3)
    assert hidden["height_bounds_cm"][0] <= top - soil <= hidden["height_bounds_cm"][1]
    assert hidden["height_cm"] == pytest.approx(top - low)
    above = {**rim, "rim_z_cm": low - 2.0, "soil_z_cm": low - 2.0}  # the plant's lowest point 2 cm above the rim
    lost = traits_workspace(_measured_workspace(tmp_path / "lost", pts, cols, [0.9] * 20, pot=above), figure=False)
    assert lost["quality"] == "failed" and "plant_base_into_pot_cm" in {c["name"] for c in lost["checks"]
                                                                         if not c["passed"]}
    # what reaches deeper below the rim than the soil is looked for is not the plant's base (a stray piece down to
    # the pot's floor made a height 50 % too tall look sure: its bounds as narrow as the ground allows)
    deep = {**rim, "rim_z_cm": low + 8.0, "soil_z_cm": low + 8.0}
    sunk = traits_workspace(_measured_workspace(tmp_path / "sunk", pts, cols, [0.9] * 20, pot=deep), figure=False)
    assert sunk["quality"] == "failed" and "plant_base_depth_in_pot_cm" in {c["name"] for c in sunk["checks"]
                                                                            if not c["passed"]}
    ground = traits_workspace(_measured_workspace(tmp_path / "ground", pts, cols, [0.9] * 20), figure=False)
    assert ground["quality"] == "ok" and "soil_interval_cm" not in ground
    assert ground["height_bounds_cm"] == pytest.approx([top - low] * 2, abs=1e-3)


def test_widths_along_axes_the_crown_does_not_fix_are_a_warning_with_their_bounds(tmp_path):
    """Synthetic demo seed 404 (2026-11-27): a nearly round crown, whose PCA axes turned 67 degrees from the truth's,
    gave width 1 25 % wide as `ok`. Four equal leaves at right angles, two of them sampled three times as densely: the
    widths come with bounds that cover every direction, and a warning; the same leaves made elongated are `ok`."""
    from plantsplat.traits.stage import run as traits_workspace

    rng = np.random.default_rng(7)
    cube = cube_surface_points(10.0, 6000, rng, faces=CUBE_FACES)

    def crown(lengths, dense_x):
        leaves = []
        for a, L in zip((0, 90, 180, 270), lengths):
            n = 1500 * (dense_x if a in (0, 180) else 1)
            c, s = np.cos(np.radians(a)), np.sin(np.radians(a))
            u, v = np.array([c, s]), np.array([-s, c])
            t, w = rng.uniform(0, L, n), rng.uniform(-1.5, 1.5, n)
            leaves.append(np.column_stack([[30.0, 5.0] + np.outer(t, u) + np.outer(w, v), 12.0 + 0.3 * t]))
        stem = np.column_stack([np.full(200, 30.0), np.full(200, 5.0), np.linspace(2.0, 12.0, 200)])
        pts = np.concatenate(leaves + [stem, cube])
        return pts, np.tile(np.array([50, 110, 40], np.uint8), (len(pts), 1))

    round_ = traits_workspace(_measured_workspace(tmp_path / "round", *crown((15, 15, 15, 15), 3), [0.9] * 20),
                              figure=False)
    assert round_["width_axis_turn_deg"] > 40.0  # the even sample has no major axis: 45 degrees and more
    assert round_["quality"] == "warning"
    assert [c["name"] for c in round_["checks"] if not c["passed"]] == ["width_bounds_reach_share"]
    lo, hi = round_["width1_bounds_cm"]
    assert lo < 0.8 * round_["width1_cm"] and hi == pytest.approx(round_["width1_cm"], rel=0.01)
    long = traits_workspace(_measured_workspace(tmp_path / "long", *crown((22, 7, 22, 7), 3), [0.9] * 20), figure=False)
    assert long["quality"] == "ok", long["quality_reasons"]
    assert long["width_axis_turn_deg"] < 5.0
    for k in ("width1", "width2"):
        lo, hi = long[f"{k}_bounds_cm"]
        assert lo <= long[f"{k}_cm"] <= hi and max(long[f"{k}_cm"] - lo, hi - long[f"{k}_cm"]) < 0.05 * long[f"{k}_cm"]


def test_height_bounds_widen_with_the_scale_error():
    from plantsplat.traits.height import SoilInterval, height_bounds, soil_interval

    assert soil_interval(10.0, True, 0.5, None) == SoilInterval(9.75, 10.25, "seen")
    hidden = soil_interval(12.0, False, 0.5, 9.0)  # the rim at 12 cm, the plant's lowest point in the pot at 9 cm
    assert (hidden.low, hidden.high) == (0.0, 9.0)
    assert height_bounds(30.0, None, 0.01, extent=20.0) == pytest.approx((19.6, 20.4))
    assert height_bounds(30.0, hidden, None) == (21.0, 30.0)


def test_a_tiny_cloud_fails_its_checks(tmp_path):
    """142 Gaussians of a wrong camera model: a plant 1.2 cm tall."""
    rng = np.random.default_rng(5)
    cube = cube_surface_points(10.0, 6000, rng, faces=CUBE_FACES)
    plant = rng.normal([24.0, 3.0, 12.0], [1.0, 0.8, 0.4], (142, 3))
    pts = np.concatenate([cube, plant])
    cols = np.concatenate([np.full((len(cube), 3), 230, np.uint8), np.full((142, 3), (40, 95, 25), np.uint8)])
    from plantsplat.traits.stage import run as traits_workspace

    out = traits_workspace(_measured_workspace(tmp_path, pts, cols), TraitsConfig(min_points=5), figure=False)
    assert out["quality"] == "failed"
    failed = {c["name"] for c in out["checks"] if not c["passed"]}
    assert {"plant_points", "plant_height_cm"} <= failed


def test_a_capture_the_poses_stage_warned_about_is_at_least_a_warning(tmp_path):
    """poses.json's warnings (e.g. frames left out) reach the traits' verdict: not `ok`, and the reason is given."""
    from plantsplat.cli import main

    pts, cols, _ = make_plant_scene(seed=8)
    ws = tmp_path / "plant_02"
    _write_points_ply(ws / "export" / "points.ply", pts, cols, np.full(len(pts), 0.9))
    left_out = {"name": "registered_share_all", "value": 0.9, "threshold": 0.95, "op": ">=", "passed": False,
                "severity": "warn", "detail": "12 frame(s) left out; the later stages use the 108 others"}
    (ws / "poses.json").write_text(json.dumps({"scale_source": "aruco", "status": "warning", "checks": [left_out]}))
    assert main(["traits", str(ws)]) == 0
    out = json.loads((ws / "traits.json").read_text())
    assert out["quality"] == "warning"
    assert any("12 frame(s) left out" in r for r in out["quality_reasons"]), out["quality_reasons"]


def test_a_base_spread_over_the_pot_is_not_the_plant_s_base():
    """Issue 41 (foreign renders 101 and 104): with the soil hidden, Gaussians of the soil taken for plant made the
    plant's lowest centimetre in the pot a layer spread over the pot's inside; a crown stands near the axis."""
    rng = np.random.default_rng(7)
    pts, cols, plant = make_plant_scene(seed=4, floaters=False)
    P = pts[plant]
    crown = P[np.argmin(P[:, 2])]
    disc = (crown[:2], 6.4)
    base = measure_traits(pts, cols, calibrated=True, soil_z=crown[2] + 1.0, soil_disc=disc)
    a, r = rng.uniform(0, 2 * np.pi, 6000), 6.4 * np.sqrt(rng.uniform(0, 1, 6000))
    soil = np.stack([crown[0] + r * np.cos(a), crown[1] + r * np.sin(a), np.full(6000, crown[2] - 0.3)], 1)
    leak = measure_traits(np.concatenate([pts, soil]), np.concatenate([cols, np.full((6000, 3), (90, 60, 30), np.uint8)]),
                          calibrated=True, soil_z=crown[2] + 1.0, soil_disc=disc)
    assert base.base_spread is not None and base.base_spread < 0.5
    assert leak.base_spread is not None and leak.base_spread > 0.6
    assert leak.soil_z == pytest.approx(crown[2] - 0.3)


def test_a_top_lost_after_the_3d_decision_fails():
    """Issue 41 (synthetic seed 82): the segment stage decided the plant up to 23.5 cm, the trained model ended at
    22.1 cm (a flower on a thin stalk, cut out of half the masks, was lost in training): the height came out 16 % short.
    A measured top at or above the decided one (it is measured at the Gaussians' extents) passes."""
    from plantsplat.checks import quality
    from plantsplat.traits.checks import result_checks

    traits = {"height_cm": 10.1}
    lost = result_checks(traits, 50_000, 22.1, 40.0, 10.0, decided_top_cm=23.5)
    kept = result_checks(traits, 50_000, 23.7, 40.0, 10.0, decided_top_cm=23.5)
    unknown = result_checks(traits, 50_000, 22.1, 40.0, 10.0)
    assert quality(lost) == "failed" and quality(kept) == "ok" and quality(unknown) == "ok"
    assert [c.name for c in lost if not c.passed] == ["plant_top_short_of_decided_share"]


def test_a_top_above_the_highest_cameras_warns_and_does_not_fail():
    """Foreign render 108: the plant's true top is 1.8 cm above the highest camera, and its height was measured within
    1.1 %. A top above the cameras is worth a warning (they saw it only from below), not a failed result."""
    from plantsplat.checks import quality
    from plantsplat.traits.checks import result_checks

    above = result_checks({"height_cm": 23.2}, 50_000, 36.0, 34.2, 10.0)
    below = result_checks({"height_cm": 23.2}, 50_000, 33.0, 34.2, 10.0)
    assert quality(above) == "warning" and quality(below) == "ok"
    assert [c.name for c in above if not c.passed] == ["plant_top_below_cameras_cm"]

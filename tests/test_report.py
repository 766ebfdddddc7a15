"""Report without a browser: .splat encoding against the PLY fields, sections present or named as missing,
bad input, the batch report's tables and links, the CLI."""

from __future__ import annotations

import base64
import json
import re

import numpy as np
import pytest
from report_workspace import (
    make_synthetic_workspace,
    synthetic_gaussians,
    write_inria_ply,
)

from plantsplat.cli import main as cli_main
from plantsplat.errors import PlantsplatError
from plantsplat.report.batch import write_batch_report
from plantsplat.report.config import ReportConfig
from plantsplat.report.figures import read_cameras
from plantsplat.report.plant import write_report
from plantsplat.report.splat import (
    SPLAT_DTYPE,
    decode_splat,
    encode_splat,
    read_points_ply,
    read_splat_ply,
)
from plantsplat.segment.preview import overlay


@pytest.fixture(scope="module")
def full_ws(tmp_path_factory):
    return make_synthetic_workspace(tmp_path_factory.mktemp("report") / "plant", n_gaussians=3000, n_frames=8)


def test_splat_encoding_matches_ply_fields(tmp_path):
    g = synthetic_gaussians(2000, seed=3)
    g["quats"] = g["quats"] * np.random.default_rng(1).uniform(0.5, 3.0, (2000, 1)).astype(np.float32)  # unnormalised
    write_inria_ply(tmp_path / "s.ply", g)
    arrays = read_splat_ply(tmp_path / "s.ply")
    rec = decode_splat(encode_splat(arrays))
    assert SPLAT_DTYPE.itemsize == 32 and len(rec) == 2000
    # match every record back to its source Gaussian by position (positions are stored exactly)
    key = {tuple(p): i for i, p in enumerate(g["means"].tolist())}
    idx = np.array([key[tuple(p)] for p in rec["position"].tolist()])
    assert sorted(idx.tolist()) == list(range(2000))
    np.testing.assert_allclose(rec["scale"], np.exp(g["log_scales"][idx]), rtol=1e-6)
    rgb = np.clip(0.5 + 0.28209479177387814 * g["f_dc"][idx], 0, 1) * 255
    assert np.abs(rec["rgba"][:, :3] - rgb).max() <= 0.51
    alpha = 255 / (1 + np.exp(-g["opacity"][idx]))
    assert np.abs(rec["rgba"][:, 3] - alpha).max() <= 0.51
    q = g["quats"][idx] / np.linalg.norm(g["quats"][idx], axis=1, keepdims=True)
    assert np.abs((rec["rot"].astype(float) - 128) / 128 - q).max() <= 1 / 128 + 1e-6
    # most visible first: opacity x volume is non-increasing
    imp = (rec["rgba"][:, 3] / 255.0) * np.prod(rec["scale"].astype(float), axis=1)
    true_imp = (1 / (1 + np.exp(-g["opacity"][idx]))) * np.exp(g["log_scales"][idx].sum(1))
    assert np.all(np.diff(true_imp) <= 1e-9) and imp[0] >= imp[-1]


def test_splat_cap_keeps_most_visible(tmp_path):
    g = synthetic_gaussians(500, seed=1)
    write_inria_ply(tmp_path / "s.ply", g)
    arrays = read_splat_ply(tmp_path / "s.ply")
    rec = decode_splat(encode_splat(arrays, max_gaussians=100))
    imp = (1 / (1 + np.exp(-g["opacity"]))) * np.exp(g["log_scales"].sum(1))
    kept = {tuple(p) for p in rec["position"].tolist()}
    top = {tuple(p) for p in g["means"][np.argsort(-imp)[:100]].tolist()}
    assert kept == top


def test_bad_plys_raise_one_line_errors(tmp_path):
    (tmp_path / "junk.ply").write_bytes(b"not a ply at all\n")
    with pytest.raises(PlantsplatError, match="junk.ply"):
        read_splat_ply(tmp_path / "junk.ply")
    from plantsplat.ply import write_point_cloud as write_points_ply

    write_points_ply(tmp_path / "pts.ply", np.zeros((5, 3), np.float32), np.zeros((5, 3), np.uint8))
    with pytest.raises(PlantsplatError, match="not a 3D Gaussian Splatting PLY"):
        read_splat_ply(tmp_path / "pts.ply")
    pc = read_points_ply(tmp_path / "pts.ply")
    assert pc.positions.shape == (5, 3) and pc.colors.dtype == np.uint8


def test_overlay_mask_darkens_background_only():
    rgb = np.full((60, 80, 3), 200, np.uint8)
    mask = np.zeros((60, 80), np.uint8)
    mask[10:50, 20:60] = 255
    out = overlay(rgb, mask)
    assert (out[30, 40] == 200).all()  # inside the mask, away from the outline: untouched
    assert out[2, 2].sum() < 0.6 * 3 * 200  # background dimmed (and tinted)
    r, g, b = (int(v) for v in out[10, 40])  # the outline (yellow, anti-aliased) on the mask border
    assert r > 200 and g > 180 and b < 80


def test_full_report_has_every_section(full_ws):
    path = write_report(full_ws)
    text = path.read_text()
    assert path == full_ws / "report.html"
    for sec in ("summary", "traits", "viewer", "renders", "metrics", "frames", "segmentation", "cameras", "runtimes"):
        assert f'<section id="{sec}">' in text
    assert "Missing:" not in text
    assert 'alt="3D decision"' in text and 'alt="least sure masks"' in text and "least 0.83" in text
    assert "PlantsplatViewerLib" in text and "http://" not in text.split("<script")[0]
    # no external resources: every src= is a data: URI and there is no <script src>
    assert not re.search(r'<script[^>]+src=', text)
    assert all(s.startswith("data:") for s in re.findall(r'src="([^"]+)"', text))
    # the embedded splat decodes to all 3000 Gaussians at the workspace's positions
    b64 = re.search(r'id="splat-data">([^<]+)</script>', text).group(1)
    rec = decode_splat(base64.b64decode(b64))
    ply = read_splat_ply(full_ws / "export" / "splat.ply")
    assert len(rec) == 3000
    assert {tuple(p) for p in rec["position"].tolist()} == {tuple(p) for p in ply.means.tolist()}
    cfg = json.loads(re.search(r'id="viewer-config">([^<]+)</script>', text).group(1))
    assert cfg["splat"] and cfg["points"] and cfg["radius"] > 1
    traits = json.loads((full_ws / "traits.json").read_text())
    assert f"{traits['height_cm']:.2f}" in text and "Fruit count" in text
    assert "frame_00000: ground truth (left)" in text
    assert "27.31" in text  # metrics.json psnr, shown generically


def test_the_viewer_shows_the_plant_alone_where_the_traits_stage_wrote_it(tmp_path):
    """plant.ply is the splat the viewer shows where the traits stage's record says it measured export/splat.ply as it
    is now; not once the model is exported again, nor where the traits measured another cloud (--points)."""
    import os

    from plantsplat.ply import write_splat_rows
    from plantsplat.stages import run_stage
    from plantsplat.workspace import Workspace

    ws = make_synthetic_workspace(tmp_path / "w", n_gaussians=400, n_frames=3, stages=("frames", "poses", "export"))
    w = Workspace(ws)
    splat, plant = ws / "export" / "splat.ply", ws / "plant.ply"

    def traits(inputs):  # the traits stage's record over ``inputs``, and its plant.ply
        run_stage(w, "traits", {}, inputs, [plant], lambda _: write_splat_rows(plant, splat, np.arange(0, 400, 4)) or {},
                  force=True)

    def shown():
        text = write_report(ws).read_text()
        b64 = re.search(r'id="splat-data">([^<]+)</script>', text).group(1)
        return {tuple(p) for p in decode_splat(base64.b64decode(b64))["position"].tolist()}, text

    traits([splat])
    positions, text = shown()
    assert positions == {tuple(p) for p in read_splat_ply(plant).means.tolist()} and len(positions) == 100
    assert "of the plant alone (plant.ply)" in text
    st = splat.stat()
    os.utime(splat, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))  # exported again since
    positions, text = shown()
    assert len(positions) == 400 and "plant alone" not in text
    other = tmp_path / "other.ply"
    other.write_bytes(splat.read_bytes())
    traits([other])  # measured on another cloud
    positions, text = shown()
    assert len(positions) == 400 and "plant alone" not in text


def test_traits_of_a_model_made_anew_since_are_said_to_be_out_of_date(tmp_path):
    """`plantsplat train --force`, then `plantsplat report`: the traits shown are of the previous model's export."""
    import os

    from plantsplat.stages import run_stage
    from plantsplat.workspace import Workspace

    ws = make_synthetic_workspace(tmp_path / "w", n_gaussians=200, n_frames=3)
    w, model, splat = Workspace(ws), ws / "model.bin", ws / "export" / "splat.ply"
    model.write_bytes(b"model")

    def train():
        run_stage(w, "train", {}, [], [model], lambda _: os.utime(model) or {}, force=True)

    train()
    run_stage(w, "export", {}, [model], [splat], lambda _: {}, force=True)
    run_stage(w, "traits", {}, [splat], [ws / "traits.json"], lambda _: {}, force=True)
    assert "OUT OF DATE" not in write_report(ws).read_text()
    model.write_bytes(b"a model trained anew")
    train()
    text = write_report(ws).read_text()
    assert "OUT OF DATE: these traits were not measured on the model as it is now" in text
    assert f"plantsplat export {ws}" in text


def test_partial_workspace_names_missing_parts(tmp_path):
    ws = make_synthetic_workspace(tmp_path / "p", n_frames=4, stages=("frames", "segment"))
    text = write_report(ws).read_text()
    for what in ("traits (traits.json)", "Gaussian splat (export/splat.ply)", "camera poses (transforms.json)",
                 "test-view renders", "image metrics (metrics.json)", "run times (run.json)"):
        assert f"<b>Missing:</b> {what}" in text, what
    assert f"plantsplat poses {ws}" in text and f"plantsplat export {ws}" in text
    assert 'id="viewer-canvas"' not in text and "PlantsplatViewerLib" not in text
    assert 'alt="contact sheet"' in text


def test_empty_and_corrupt_inputs_still_give_a_report(tmp_path):
    ws = tmp_path / "empty"
    ws.mkdir()
    text = write_report(ws).read_text()
    assert text.count("<b>Missing:</b>") >= 8
    ws2 = make_synthetic_workspace(tmp_path / "bad", n_gaussians=200, n_frames=3, stages=("frames", "poses", "traits", "export"))
    (ws2 / "traits.json").write_text("{not json")
    (ws2 / "transforms.json").write_text(json.dumps({"frames": [{"transform_matrix": [[1, 2]]}]}))
    (ws2 / "export" / "splat.ply").write_bytes(b"ply\nformat nonsense\n")
    text = write_report(ws2).read_text()
    assert "Could not show this part" in text and "traits.json: not valid JSON" in text
    assert "transforms.json: transform_matrix entries are not 4x4" in text
    assert "splat.ply: not a readable PLY" in text
    assert 'id="points-xyz"' in text  # the point cloud is still shown
    with pytest.raises(PlantsplatError, match="workspace folder not found"):
        write_report(tmp_path / "nope")


def test_read_cameras_rejects_bad_json(tmp_path):
    (tmp_path / "t.json").write_text("[1, 2")
    with pytest.raises(PlantsplatError, match="t.json"):
        read_cameras(tmp_path / "t.json")


def test_report_options_cap_sizes(full_ws, tmp_path):
    out = tmp_path / "small.html"
    write_report(full_ws, out, ReportConfig(max_gaussians=500, max_points=300, viewer=True))
    text = out.read_text()
    rec = decode_splat(base64.b64decode(re.search(r'id="splat-data">([^<]+)</script>', text).group(1)))
    xyz = base64.b64decode(re.search(r'id="points-xyz">([^<]+)</script>', text).group(1))
    assert len(rec) == 500 and len(xyz) == 300 * 12
    write_report(full_ws, out, ReportConfig(viewer=False))
    assert "PlantsplatViewerLib" not in out.read_text()


def test_cli(full_ws, tmp_path, capsys):
    out = tmp_path / "r.html"
    assert cli_main(["report", str(full_ws), "--out", str(out), "--max-points", "1000"]) == 0
    assert out.is_file() and out.stat().st_size > 3_000_000
    assert cli_main(["report", str(tmp_path / "missing_ws")]) == 2
    assert cli_main(["report", str(full_ws), "--max-gaussians", "0"]) == 2
    assert "error:" in capsys.readouterr().err


def _batch_inputs(tmp_path):
    rows = [
        {"plant_id": "p1", "status": "ok", "error": None, "height_cm": 20.0, "width1_cm": 30.0, "fruit_count": 3},
        {"plant_id": "p2", "status": "ok", "error": None, "height_cm": 25.0, "width1_cm": 34.0, "fruit_count": 5},
        {"plant_id": "p3", "status": "failed", "error": "poses: too few cameras registered"},
    ]
    accuracy = {"table": {"height_cm": {"n": 2, "r2": 0.91, "rmse": 0.71, "mape": 2.9, "mae": 0.7, "acc": 97.1},
                          "width1_cm": {"n": 2, "r2": 0.5, "rmse": 1.2, "mape": 3.5, "mae": 1.1, "acc": 96.5}},
                "ground_truth_problems": [], "plants_without_ground_truth": []}
    truth = {"p1": {"height_cm": 20.5, "width1_cm": 31.0}, "p2": {"height_cm": 24.1, "width1_cm": 33.0}}
    (tmp_path / "plants" / "p1").mkdir(parents=True)
    (tmp_path / "plants" / "p1" / "report.html").write_text("<html></html>")
    return rows, accuracy, truth, {"p1": tmp_path / "plants" / "p1" / "report.html"}


def test_batch_report_tables_links_and_scatter(tmp_path):
    rows, accuracy, truth, reports = _batch_inputs(tmp_path)
    path = write_batch_report(tmp_path, rows, accuracy, reports, truth=truth)
    text = path.read_text()
    assert '<a href="plants/p1/report.html">p1</a>' in text
    assert "poses: too few cameras registered" in text
    assert "0.91" in text and "97.10" in text and "MAPE (%)" in text
    assert text.count('class="scatter"') == 2  # height and width1 have truth
    assert "cdn.plot.ly" not in text.split("<main>")[1] and "Plotly.newPlot" in text
    # without ground truth: the accuracy and plots are named as missing, no plotly.js
    text = write_batch_report(tmp_path / "nogt", rows, None, {}).read_text()
    assert "accuracy table (no ground truth given)" in text and "Plotly.newPlot" not in text
    # truth given as <trait>_gt columns
    rows_gt = [dict(r, height_cm_gt=21.0) for r in rows[:2]]
    text = write_batch_report(tmp_path / "gtcols", rows_gt, accuracy, {}).read_text()
    assert text.count('class="scatter"') == 1


def test_batch_report_computes_accuracy_from_truth(tmp_path):
    rows = [{"plant_id": f"p{i}", "status": "ok", "height_cm": 20.0 + i} for i in range(4)]
    truth = {f"p{i}": {"height_cm": 20.5 + 0.9 * i} for i in range(4)}  # errors 0.5, 0.4, 0.3, 0.2 cm
    text = write_batch_report(tmp_path, rows, None, {}, truth=truth).read_text()
    acc = re.sub(r"<[^>]+>", " ", text[text.index('id="accuracy"'):text.index('id="scatter"')])
    assert re.search(r"height_cm\s+4\s+[-\d.]+\s+[\d.]+\s+[\d.]+\s+0\.35\b", acc), acc  # n = 4, MAE = 0.35


def test_generic_metrics_tables_flatten_nested_records():
    from plantsplat.report.html import generic_tables

    html = generic_tables({"mode": "object", "composite": {"psnr": 39.04}, "per_view": [
        {"name": "frame_00001.png", "composite": {"psnr": 40.1, "ssim": 0.99}},
        {"name": "frame_00004.png", "composite": {"psnr": 38.2}}]})
    assert "<th>composite psnr</th><th>composite ssim</th>" in html
    assert "<td>frame_00004.png</td><td>38.20</td><td>&ndash;</td>" in html
    assert "<h4>composite</h4>" in html and "39.04" in html


def test_real_capture_cameras_look_at_the_plant(datasets_dir, tmp_path):
    """ROMI scanner: 60 views on a 300 mm circle; OpenGL -z of every camera points at the circle's centre."""
    import shutil

    src = datasets_dir / "romi_real_plant"
    if not (src / "transforms.json").is_file():
        pytest.skip(f"{src}/transforms.json not found")
    c2w, names = read_cameras(src / "transforms.json")
    centres = c2w[:, :3, 3]
    mid = centres.mean(0)
    dist = np.linalg.norm(centres - mid, axis=1)
    assert len(c2w) == 60 and abs(dist.mean() - 300) < 15 and dist.std() / dist.mean() < 0.05
    look = -c2w[:, :3, 2]
    to_mid = (mid - centres) / dist[:, None]
    assert np.median(np.sum(look * to_mid, axis=1)) > 0.8
    ws = tmp_path / "romi"
    (ws / "images").mkdir(parents=True)
    shutil.copy(src / "transforms.json", ws / "transforms.json")
    for name in sorted(p.name for p in (src / "images").iterdir())[:3]:
        shutil.copy(src / "images" / name, ws / "images" / name)
    text = write_report(ws, opts=ReportConfig(max_frames=3)).read_text()
    assert "registered cameras</th><td>60</td>" in text and 'alt="camera path"' in text
    assert "3 of 3 frames" in text

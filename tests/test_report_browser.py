"""Reports opened from file:// in headless Chromium (Debian `chromium` + Playwright's Python API):
the splat viewer draws the plant (its red fruit included) in both modes, plotly draws the batch
scatter plots, and no console errors occur. Screenshots go to $PLANTSPLAT_TEST_ARTIFACTS (or tmp)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from report_workspace import make_synthetic_workspace

from plantsplat.report.batch import write_batch_report
from plantsplat.report.browser import (
    ReportBrowser,
    find_chromium,
    open_report,
    playwright_available,
)
from plantsplat.report.plant import write_report

pytestmark = [
    pytest.mark.skipif(find_chromium() is None,
                       reason="chromium not installed (apt-get install chromium) - browser tests skipped"),
    pytest.mark.skipif(not playwright_available(),
                       reason="playwright not installed (pip install playwright; no browser download needed)"),
]


def _artifacts(tmp_path: Path) -> Path:
    d = Path(os.environ.get("PLANTSPLAT_TEST_ARTIFACTS", tmp_path))
    d.mkdir(parents=True, exist_ok=True)
    return d


def test_plant_report_viewer_draws_splat_and_points(tmp_path):
    ws = make_synthetic_workspace(tmp_path / "plant", n_gaussians=4000, n_frames=6)
    report = write_report(ws)
    shot = _artifacts(tmp_path) / "report_plant.png"
    res = open_report(report, screenshot=shot, modes=("points", "splat"), timeout_s=90, orbit_frames=3)
    assert res.console_errors == []
    assert res.viewer_state == "ready", res.viewer_error
    assert res.first_content_s is not None
    # the splat covers a good part of the canvas; points alone cover less but are drawn too
    assert res.canvas_fraction > 0.03
    assert res.mode_fractions["splat"] > 0.03 and res.mode_fractions["points"] > 0.005
    assert res.mode_fractions["points"] < res.mode_fractions["splat"]
    img = res.canvas_image.astype(int)  # [H, W, 3] splat view
    red = (img[..., 0] > 150) & (img[..., 1] < 90) & (img[..., 2] < 90)  # the three red berries
    green = (img[..., 1] > img[..., 0] + 30) & (img[..., 1] > img[..., 2] + 30)  # leaves
    assert red.sum() > 50 and green.sum() > 20 * red.sum() / 10
    # the plant is framed: drawn pixels are centred in the canvas
    ys, xs = np.nonzero(np.abs(img - [0x20, 0x21, 0x24]).sum(-1) > 60)
    h, w = img.shape[:2]
    assert abs(xs.mean() / w - 0.5) < 0.2 and abs(ys.mean() / h - 0.5) < 0.25
    assert shot.is_file() and shot.stat().st_size > 10_000
    assert res.orbit["frames"] == 3 and res.orbit["fps"] > 0


def test_batch_and_partial_reports_open_without_errors(tmp_path):
    part = make_synthetic_workspace(tmp_path / "partial", n_frames=3, stages=("frames",))
    rows = [{"plant_id": f"p{i}", "status": "ok", "height_cm": 20.0 + i, "width1_cm": 30.0 - i} for i in range(4)]
    truth = {f"p{i}": {"height_cm": 20.5 + 0.9 * i, "width1_cm": 29.0 - i} for i in range(4)}
    out = write_batch_report(tmp_path / "batch", rows, None, {"p0": write_report(part)}, truth=truth)
    pts = make_synthetic_workspace(tmp_path / "pts", n_gaussians=3000, n_frames=2, stages=("export",))
    (pts / "export" / "splat.ply").unlink()  # a point cloud but no splat: the viewer shows the points
    with ReportBrowser() as browser:
        res = browser.open(part / "report.html", screenshot=_artifacts(tmp_path) / "report_partial.png")
        assert res.console_errors == [] and res.viewer_state is None
        res = browser.open(write_report(pts))
        assert res.console_errors == [] and res.viewer_state == "ready" and res.canvas_fraction > 0.003
        res = browser.open(out, screenshot=_artifacts(tmp_path) / "report_batch.png", keep_page=True)
        page = res.page
        page.wait_for_selector(".scatter .main-svg", timeout=30_000)
        n_plots = page.locator(".scatter .js-plotly-plot").count()
        n_markers = page.locator(".scatter .scatterlayer .point").count()
        href = page.locator("a", has_text="p0").get_attribute("href")
        page.close()
    assert res.console_errors == []
    assert n_plots == 2 and n_markers == 8  # 4 plants x 2 traits
    assert (out.parent / href).resolve() == (part / "report.html").resolve()


def test_without_webgl_the_viewer_says_so(tmp_path):
    ws = make_synthetic_workspace(tmp_path / "pts", n_gaussians=300, n_frames=2, stages=("export",))
    with ReportBrowser(extra_args=("--disable-webgl", "--disable-3d-apis")) as browser:
        res = browser.open(write_report(ws), keep_page=True)
        message = res.page.locator("#viewer-message").inner_text()
        res.page.close()
    assert res.viewer_state == "error" and "WebGL" in message

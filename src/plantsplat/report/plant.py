"""The per-plant report: one self-contained ``report.html`` built from whatever the workspace holds.

Sections: what exists and what is missing; traits with the measurement figure; an interactive 3D
viewer of the Gaussian splat and the point cloud (Spark + three.js, inlined); test-view renders next
to their ground-truth frames; image metrics; a contact sheet of frames with mask overlays; the camera
path; run times per stage. A part whose input is missing or unreadable is named in its place with
the command that produces it; it never stops the report.

Usage:
    from plantsplat.report.plant import write_report
    write_report("ws/plant_01")
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from plantsplat import __version__ as version
from plantsplat.errors import PlantsplatError
from plantsplat.io import read_image, read_json, write_text_atomic
from plantsplat.log import get_logger, progress
from plantsplat.report import html as H
from plantsplat.report.config import ReportConfig
from plantsplat.report.figures import (
    camera_path_png,
    frames_contact_sheet,
    pick_evenly,
    read_cameras,
    render_pairs,
)
from plantsplat.report.splat import encode_splat, read_points_ply, read_splat_ply
from plantsplat.stages import fingerprints, out_of_date, read_record
from plantsplat.traitdefs import TRAIT_KEYS, TRAIT_LABELS, TRAIT_UNITS
from plantsplat.workspace import Workspace

log = get_logger(__name__)

BACKGROUND = "#202124"


@dataclass
class _Parts:
    present: list[str] = field(default_factory=list)
    missing: list[tuple[str, str]] = field(default_factory=list)  # (what, how to get it)

    def have(self, what: str) -> None:
        self.present.append(what)

    def miss(self, what: str, hint: str) -> str:
        self.missing.append((what, hint))
        return H.missing_note(what, hint)


def _guard(parts: _Parts, label: str, fn):
    """Run one section builder or reader; an unreadable input becomes a visible note (its HTML is
    returned instead of the value), not a failed report."""
    try:
        return fn()
    except PlantsplatError as exc:
        log.warning("report: %s: %s", label, exc)
        parts.missing.append((f"{label} (unreadable)", str(exc)))
        return H.error_note(str(exc))


def _cmd(stage: str, ws: Workspace) -> str:
    return f"run `plantsplat {stage} {ws.root}`"


def _traits_section(ws: Workspace, parts: _Parts) -> str:
    body = []
    if ws.traits_json.is_file():
        t = read_json(ws.traits_json)
        if not isinstance(t, dict):
            raise PlantsplatError(f"{ws.traits_json}: expected a JSON object; re-run `plantsplat traits`")
        main = {TRAIT_LABELS[k].capitalize() + (f" ({TRAIT_UNITS[k]})" if TRAIT_UNITS[k] else ""): t[k]
                for k in TRAIT_KEYS if k in t}
        for key, label in (("quality", "Measurement quality"), ("scale_source", "Scale from")):
            if t.get(key) is not None:
                main[label] = t[key]
        body.append(H.kv_table(main, cls="kv traits"))
        reasons = t.get("quality_reasons")
        if reasons:
            items = "".join(f"<li>{H.esc(r)}</li>" for r in (reasons if isinstance(reasons, list) else [reasons]))
            body.append(f'<div class="missing"><b>Check these measurements:</b><ul>{items}</ul></div>')
        shown = {"quality", "scale_source", "quality_reasons"}
        other = {k: v for k, v in t.items() if k not in TRAIT_KEYS and k not in shown}
        if other:
            body.append("<details><summary>measurement details</summary>" + H.generic_tables(other) + "</details>")
        parts.have("traits")
    else:
        body.append(parts.miss("traits (traits.json)", _cmd("traits", ws)))
    if ws.traits_png.is_file():
        body.append("<h4>measurement figure: top view with PCA axes and widths, side view with height</h4>")
        body.append(H.img_tag(ws.traits_png.read_bytes(), "image/png", "traits figure", cls="figure"))
        parts.have("measurement figure")
    else:
        body.append(parts.miss("measurement figure (traits.png)", _cmd("traits", ws)))
    return "".join(body)


def _scene_frame(points: np.ndarray) -> tuple[list[float], float]:
    """Viewer target and radius from scene points [N, 3]: centre and half diagonal of the 1-99 % box.

    Percentiles keep a few floaters from shrinking the model to a dot.
    """
    if len(points) < 2:
        return [float(x) for x in points.mean(0)], 1.0
    lo, hi = np.percentile(points, [1, 99], axis=0)  # [3], [3]
    c = (lo + hi) / 2
    r = 0.5 * float(np.linalg.norm(hi - lo))
    return [float(x) for x in c], max(r, 1e-3)


def viewer_splat(ws: Workspace) -> Path:
    """The splat the 3D viewer shows: the plant alone (``plant.ply``) where the traits stage's record says it measured
    the exported model as it is now, else the whole model (``export/splat.ply``: the plant and the cube)."""
    measured = (read_record(ws, "traits") or {}).get("inputs") or {}
    now = fingerprints(ws, [ws.splat_ply])
    if ws.plant_ply.is_file() and all(fp is not None and measured.get(k) == fp for k, fp in now.items()):
        return ws.plant_ply
    return ws.splat_ply


def _viewer_section(ws: Workspace, parts: _Parts, opts: ReportConfig) -> str:
    if not opts.viewer:
        return '<p class="muted">3D viewer left out (--no-viewer).</p>'
    blocks, notes, stats = [], [], []
    cfg: dict = {"background": BACKGROUND, "splat": False, "points": False}
    frame_pts = None
    splat = viewer_splat(ws)
    if splat.is_file():
        g = _guard(parts, "Gaussian splat", lambda: read_splat_ply(splat))
        if isinstance(g, str):
            notes.append(g)
        elif len(g) == 0:
            notes.append(parts.miss(f"Gaussians ({splat.relative_to(ws.root)} holds none)", _cmd("train", ws)))
        else:
            raw = encode_splat(g, opts.max_gaussians)
            n_kept = len(raw) // 32
            blocks.append(H.data_block("splat-data", raw))
            cfg["splat"] = True
            cfg["splat_count"] = n_kept
            frame_pts = g.means
            stats.append(f"{n_kept:,} Gaussians" + (f" (most visible of {len(g):,})" if n_kept < len(g) else "")
                         + (" of the plant alone (plant.ply)" if splat == ws.plant_ply else ""))
            parts.have("Gaussian splat")
    else:
        notes.append(parts.miss("Gaussian splat (export/splat.ply)", _cmd("export", ws)))
    if ws.points_ply.is_file():
        pc = _guard(parts, "point cloud", lambda: read_points_ply(ws.points_ply, opts.max_points))
        if isinstance(pc, str):
            notes.append(pc)
        elif len(pc.positions) == 0:
            notes.append(parts.miss("points (export/points.ply holds none)", _cmd("export", ws)))
        else:
            blocks.append(H.data_block("points-xyz", pc.positions.astype("<f4").tobytes()))
            blocks.append(H.data_block("points-rgb", pc.colors.tobytes()))
            cfg["points"] = True
            if frame_pts is None:
                frame_pts = pc.positions
            stats.append(f"{len(pc.positions):,} points")
            parts.have("point cloud")
    else:
        notes.append(parts.miss("point cloud (export/points.ply)", _cmd("export", ws)))
    if frame_pts is None:
        return "".join(notes)
    cfg["center"], cfg["radius"] = _scene_frame(frame_pts)
    cfg["mode"] = "splat" if cfg["splat"] else "points"
    buttons = []
    if cfg["splat"]:
        buttons.append('<button data-viewer-mode="splat">Gaussian splat</button>')
    if cfg["points"]:
        buttons.append('<button data-viewer-mode="points">Point cloud</button>')
    if cfg["splat"] and cfg["points"]:
        buttons.append('<button data-viewer-mode="both">Both</button>')
    buttons += ['<button id="viewer-home">Reset view</button>', '<button id="viewer-rotate">Auto-rotate</button>']
    return (
        "".join(notes)
        + f'<div class="toolbar">{" ".join(buttons)} <span class="muted">{H.esc(" · ".join(stats))}. '
        "Drag to orbit, scroll to zoom, right-drag to pan. Grid: 5 cm cells on the ground plane (z = 0).</span></div>"
        + '<div id="viewer-wrap"><canvas id="viewer-canvas"></canvas><div id="viewer-message"></div></div>'
        + f'<script type="application/json" id="viewer-config">{json.dumps(cfg)}</script>'
        + "".join(blocks)
        + H.inline_script(H.asset_text("viewer-lib.js"))
        + H.inline_script(H.asset_text("viewer-app.js"))
    )


def _renders_section(ws: Workspace, parts: _Parts, opts: ReportConfig) -> str:
    rdir = ws.train_dir / "renders"
    pairs = render_pairs(rdir) if rdir.is_dir() else []
    if not pairs:
        return parts.miss("test-view renders (train/renders/<name>_render.png with <name>_gt.png)",
                          f"written when training evaluates the test views: `plantsplat train {ws.root}`")
    shown = pick_evenly(pairs, opts.max_render_pairs)
    cells = []
    for name, rp, gp in shown:
        r, gt = read_image(rp), read_image(gp)
        if r.shape != gt.shape:
            r = cv2.resize(r, (gt.shape[1], gt.shape[0]), interpolation=cv2.INTER_AREA)
        value = float(cv2.PSNR(r, gt))
        w = min(360, gt.shape[1])
        size = (w, max(1, round(gt.shape[0] * w / gt.shape[1])))
        imgs = [cv2.resize(x, size, interpolation=cv2.INTER_AREA) for x in (gt, r)]
        cells.append(
            f'<div class="pair"><figure><div class="imgs">{H.img_tag(H.encode_image(imgs[0]), "image/jpeg", "ground truth")}'
            f'{H.img_tag(H.encode_image(imgs[1]), "image/jpeg", "render")}</div>'
            f"<figcaption>{H.esc(name)}: ground truth (left), render (right); PSNR {value:.2f} dB</figcaption></figure></div>"
        )
    parts.have("test-view renders")
    return (f'<p class="muted">{len(shown)} of {len(pairs)} test views. PSNR computed here on the full 8-bit images.</p>'
            f'<div class="pairs">{"".join(cells)}</div>')


def _metrics_section(ws: Workspace, parts: _Parts) -> str:
    if not ws.metrics_json.is_file():
        return parts.miss("image metrics (metrics.json)", _cmd("train", ws))
    m = read_json(ws.metrics_json)
    if not isinstance(m, dict):
        raise PlantsplatError(f"{ws.metrics_json}: expected a JSON object; re-run `plantsplat train {ws.root} --force`")
    parts.have("image metrics")
    return H.generic_tables(m)


def _frames_section(ws: Workspace, parts: _Parts, opts: ReportConfig) -> str:
    names = ws.image_names()
    body = []
    if names:
        sheet, shown, masked = frames_contact_sheet(ws, opts.max_frames)
        n_masks = len(list(ws.masks_dir.glob("*.png"))) if ws.masks_dir.is_dir() else 0
        body.append(f'<p class="muted">{shown} of {len(names)} frames; {n_masks} masks in masks/. '
                    "Background darkened, mask outline in green.</p>")
        body.append(H.img_tag(H.encode_image(sheet, ".jpg", 82), "image/jpeg", "contact sheet", cls="figure"))
        parts.have("frames")
        if masked == 0:
            body.append(parts.miss("masks (masks/)", _cmd("segment", ws)))
        else:
            parts.have("masks")
    elif ws.masks_preview_png.is_file():
        body.append(parts.miss("frames (images/)", f"run `plantsplat frames VIDEO --out {ws.root}`"))
        body.append(H.img_tag(ws.masks_preview_png.read_bytes(), "image/png", "masks preview", cls="figure"))
    else:
        body.append(parts.miss("frames (images/)", f"run `plantsplat frames VIDEO --out {ws.root}`"))
    if ws.frames_json.is_file():
        fj = read_json(ws.frames_json)
        if isinstance(fj, dict):
            info = {k: v for k, v in fj.items() if not isinstance(v, (list, dict))}
            if isinstance(fj.get("frames"), list):
                info["frames listed"] = len(fj["frames"])
            if info:
                body.append("<h4>frames.json</h4>" + H.kv_table(info))
    return "".join(body)


def _segmentation_section(ws: Workspace, parts: _Parts) -> str:
    """The segment stage's 3D decision (``segment_decision.png``) and its contact sheet, least sure frames first."""
    decision, sheet = ws.segment_decision_png, ws.masks_preview_png
    if not decision.is_file() and not sheet.is_file():
        return parts.miss("segmentation figures (segment_decision.png, masks_preview.png)", _cmd("segment", ws))
    body = []
    if decision.is_file():
        body.append('<p class="muted">Every opaque Gaussian of the quick scene model near the orbit\'s axis, by what the '
                    "segment stage called it. Red: candidates the evidence set aside. Anything of the room drawn in "
                    "green was taken for plant: correct it with <code>--segment.import-masks</code>.</p>")
        body.append(H.img_tag(decision.read_bytes(), "image/png", "3D decision", cls="figure"))
        parts.have("3D decision")
    if sheet.is_file():
        conf = (read_json(ws.segment_json).get("confidence") or {}) if ws.segment_json.is_file() else {}
        sure = f" (mean {conf['mean']:.2f}, least {conf['min']:.2f})" if "mean" in conf and "min" in conf else ""
        body.append(f'<p class="muted">Masks: the frames the segmenter is least sure of first{H.esc(sure)}, then '
                    "frames spread over the capture.</p>")
        body.append(H.img_tag(sheet.read_bytes(), "image/png", "least sure masks", cls="figure"))
    return "".join(body)


def _cameras_section(ws: Workspace, parts: _Parts) -> str:
    if not ws.transforms_json.is_file():
        return parts.miss("camera poses (transforms.json)", _cmd("poses", ws))
    c2w, _ = read_cameras(ws.transforms_json)
    scene = None
    for p in (ws.points_ply, ws.sparse_points_ply):
        if p.is_file():
            try:
                scene = read_points_ply(p, max_points=3000).positions
                break
            except PlantsplatError:
                continue
    png = camera_path_png(c2w, scene)
    parts.have("camera path")
    n_frames = len(ws.image_names())
    dist = np.linalg.norm(c2w[:, :3, 3] - (np.median(scene, 0) if scene is not None else 0), axis=1)
    info = {"registered cameras": len(c2w), "frames in images/": n_frames,
            "camera distance to the scene centre (cm), median": float(np.median(dist)),
            "camera height z (cm), min / max": [float(c2w[:, 2, 3].min()), float(c2w[:, 2, 3].max())]}
    return H.kv_table(info) + H.img_tag(png, "image/png", "camera path", cls="figure")


def _fmt_seconds(s: float) -> str:
    s = float(s)
    if s < 60:
        return f"{s:.1f} s"
    m, sec = divmod(int(round(s)), 60)
    h, m = divmod(m, 60)
    return f"{h}:{m:02d}:{sec:02d}" if h else f"{m}:{sec:02d}"


def _runtimes_section(ws: Workspace, parts: _Parts) -> str:
    if not ws.run_json.is_file():
        return parts.miss("run times (run.json)", f"written by `plantsplat run VIDEO --out {ws.root}`")
    r = read_json(ws.run_json)
    stages = r.get("stages") if isinstance(r, dict) else None
    if not isinstance(stages, dict) or not stages:
        raise PlantsplatError(f"{ws.run_json}: no 'stages' with per-stage times; re-run `plantsplat run VIDEO --out {ws.root}`")
    secs = {k: float(v.get("seconds", 0) or 0) for k, v in stages.items() if isinstance(v, dict)}
    total = sum(secs.values()) or 1.0
    rows = []
    for k, v in stages.items():
        if not isinstance(v, dict):
            continue
        s = secs[k]
        status = ("failed: " + str(v["failed"])) if v.get("failed") else ("skipped (reused)" if v.get("skipped") else "ran")
        rows.append({"stage": k, "status": status, "time": _fmt_seconds(s),
                     "share": f'<span class="bar" style="width:{int(200 * s / total)}px">'
                     f"</span> {100 * s / total:.0f}%", "peak memory (MB)": v.get("peak_rss_mb"),
                     **{kk: vv for kk, vv in v.items() if kk not in {"seconds", "peak_rss_mb"} and H.is_number(vv)}})
    cols = ["stage", "status", "time", "share", "peak memory (MB)"]
    for row in rows:
        cols += [c for c in row if c not in cols]
    parts.have("run times")
    extra = {k: v for k, v in r.items() if k != "stages"}
    body = H.rows_table(rows, cols, raw_html_columns=("share", "time")) + f"<p>Total: {_fmt_seconds(sum(secs.values()))}</p>"
    if extra:
        body += "<details><summary>run details (versions, configuration)</summary>" + H.generic_tables(extra) + "</details>"
    return body


def build_report_html(ws: Workspace, opts: ReportConfig | None = None) -> tuple[str, _Parts]:
    """The report for ``ws`` as an HTML string, with the list of present and missing parts."""
    opts = opts or ReportConfig()
    parts = _Parts()
    steps = [
        ("traits", "Traits", lambda: _traits_section(ws, parts)),
        ("viewer", "3D view: Gaussian splat and point cloud", lambda: _viewer_section(ws, parts, opts)),
        ("renders", "Test views: renders next to ground truth", lambda: _renders_section(ws, parts, opts)),
        ("metrics", "Image metrics", lambda: _metrics_section(ws, parts)),
        ("frames", "Frames and masks", lambda: _frames_section(ws, parts, opts)),
        ("segmentation", "The plant found in 3D, and the least sure masks", lambda: _segmentation_section(ws, parts)),
        ("cameras", "Camera path", lambda: _cameras_section(ws, parts)),
        ("runtimes", "Run times per stage", lambda: _runtimes_section(ws, parts)),
    ]
    sections = []
    for sec_id, title, fn in progress(steps, "report sections"):
        t0 = time.perf_counter()
        sections.append(H.section(sec_id, title, _guard(parts, title, fn)))
        log.debug("report section %s: %.2f s", sec_id, time.perf_counter() - t0)
    status = "".join(f'<li class="ok">{H.esc(p)}</li>' for p in parts.present)
    status += "".join(f'<li class="no">{H.esc(w)}: <span class="muted">{H.esc(h)}</span></li>' for w, h in parts.missing)
    summary = H.section("summary", "Contents", f'<ul class="status-list">{status}</ul>')
    nav = "<nav>" + "".join(f'<a href="#{i}">{H.esc(t.split(":")[0])}</a>' for i, t, _ in steps) + "</nav>"
    when = _dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    header = (f"<header><h1>plantsplat report: {H.esc(ws.root.resolve().name)}</h1>"
              f'<div class="sub">{H.esc(str(ws.root.resolve()))} · generated {H.esc(when)} · plantsplat {H.esc(version)}'
              f" · {len(parts.missing)} part(s) missing</div></header>")
    body = header + nav + "<main>" + _failed_banner(ws) + _out_of_date_banner(ws) + summary + "".join(sections) + "</main>"
    return H.page(f"plantsplat report: {ws.root.resolve().name}", body), parts


def _failed_banner(ws: Workspace) -> str:
    """A failed result, said first: before any number of it is read."""
    if not ws.traits_json.is_file():
        return ""
    try:
        t = read_json(ws.traits_json)
    except PlantsplatError:
        return ""
    if not isinstance(t, dict) or t.get("quality") != "failed":
        return ""
    items = "".join(f"<li>{H.esc(r)}</li>" for r in t.get("quality_reasons", [])[:6])
    return (f'<div class="missing failed"><b>RESULT FAILED: these traits must not be used.</b> '
            f"The checks that failed:<ul>{items}</ul></div>")


def _out_of_date_banner(ws: Workspace) -> str:
    """Traits measured on what a stage has made anew since (``plantsplat train --force`` and no export or traits
    after it): said first, with the command that brings them up to date."""
    if not ws.traits_json.is_file():
        return ""
    stale = out_of_date(ws, "traits")
    if stale is None:
        return ""
    first, writer, path = stale
    return (f'<div class="missing failed"><b>OUT OF DATE: these traits were not measured on the model as it is '
            f"now.</b> The {H.esc(writer)} stage wrote {H.esc(path)} again after the {H.esc(first)} stage ran; run "
            f"<code>plantsplat {H.esc(first)} {H.esc(str(ws.root))}</code> and the stages after it, then the report "
            "again.</div>")


def write_report(workspace: Workspace | str | os.PathLike, out: str | os.PathLike | None = None,
                 opts: ReportConfig | None = None) -> Path:
    """Write the plant report for ``workspace`` to ``out`` (default ``WS/report.html``), atomically.

    Missing or unreadable parts are named in the report; only a missing workspace folder is an error.

    Usage:
        write_report("ws/plant_01")
    """
    ws = workspace if isinstance(workspace, Workspace) else Workspace(workspace)
    if not ws.root.is_dir():
        raise PlantsplatError(f"{ws.root}: workspace folder not found; give the folder a plantsplat stage wrote into",
                              exit_code=2)
    out_path = Path(out) if out is not None else ws.report_html
    if out_path.exists() and out_path.is_dir():
        raise PlantsplatError(f"{out_path}: is a folder; give a file name for --out", exit_code=2)
    t0 = time.perf_counter()
    text, parts = build_report_html(ws, opts)
    write_text_atomic(out_path, text)
    log.info("report: %s (%.1f MB, %d parts, %d missing) in %.1f s", out_path, len(text.encode()) / 1e6,
             len(parts.present), len(parts.missing), time.perf_counter() - t0)
    return out_path

"""The traits stage over a workspace: what it reads, what it writes, and :func:`run`.

It reads the exported model (``WS/export/splat.ply``, the Gaussians with their extents sampled, or
``WS/export/points.ply``, their centres), the poses stage's calibration and cube, the segment stage's
pot and the other stages' records for their checks; it writes ``WS/traits.json``, ``traits.csv``, ``traits.png``
and ``plant.ply`` (the plant's Gaussians alone, without the cube and what was left out). The measurement itself is
:func:`plantsplat.traits.measure.measure_traits`; the verdict, :mod:`plantsplat.traits.checks`; the height's bounds,
:mod:`plantsplat.traits.height`; the widths', :mod:`plantsplat.traits.widths`.

Usage:
    from plantsplat.traits import stage
    out = stage.run(Workspace("ws/plant_01"))
    out["height_cm"], out["quality"]
"""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import numpy as np

from plantsplat import traitdefs
from plantsplat.checks import quality
from plantsplat.errors import PlantsplatError
from plantsplat.io import csv_cell, read_json, write_json_atomic, write_text_atomic
from plantsplat.log import get_logger
from plantsplat.markers import recorded_cube
from plantsplat.ply import is_splat, read_point_cloud, read_splat_extent_cloud, write_splat_rows
from plantsplat.segment.object3d import POT_SLAB_CM
from plantsplat.train.data import load_scene
from plantsplat.traits.checks import result_checks, stage_checks, workspace_soil
from plantsplat.traits.config import ROBUST_KEYS, MeasureConfig, TraitsConfig, cube_edge_cm
from plantsplat.traits.figures import traits_figure
from plantsplat.traits.fruit_views import judge_by_views
from plantsplat.traits.height import height_bounds, soil_interval
from plantsplat.traits.measure import measure_traits
from plantsplat.traits.result import TraitResult
from plantsplat.traits.widths import axis_turn_deg, footprint_range, width_bounds
from plantsplat.workspace import Workspace

log = get_logger(__name__)


def inputs(ws: Workspace, points: Path | None = None) -> list[Path]:
    """The files the stage reads (``points``: a PLY measured instead of the workspace's export)."""
    clouds = [Path(points)] if points is not None else [ws.splat_ply, ws.points_ply]
    return [*clouds, ws.poses_json, ws.markers_json, ws.segment_json, ws.metrics_json, ws.transforms_json]


def outputs(ws: Workspace) -> list[Path]:
    """The files the stage writes (and its record checks); ``traits.png`` is a figure of them, and ``plant.ply`` the
    Gaussians they were measured on (both written where there is a plant)."""
    return [ws.traits_json, ws.traits_csv]


def traits_csv_text(result_json: dict, plant: str) -> str:
    """One header line and one row: plant, the six traits, robust height/widths, scale, quality."""
    cols = ["plant", *traitdefs.TRAIT_KEYS, *(f"robust_{k}" for k in ROBUST_KEYS), "scale_source",
            "aruco_vs_cube_pct", "quality", "quality_reasons"]
    sc = result_json.get("scale") or {}
    row = [plant, *(result_json.get(k) for k in traitdefs.TRAIT_KEYS),
           *((result_json.get("robust") or {}).get(k) for k in ROBUST_KEYS), sc.get("source"),
           sc.get("aruco_vs_cube_pct"), result_json.get("quality"), " | ".join(result_json.get("quality_reasons", []))]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(cols)
    w.writerow(["" if x is None else (f"{x:.4f}" if isinstance(x, float) else csv_cell(x)) for x in row])
    return buf.getvalue()



def camera_centres(ws) -> np.ndarray | None:
    """Camera positions from ``transforms.json`` (camera-to-world matrices), or None."""
    if not ws.transforms_json.is_file():
        return None
    try:
        tf = json.loads(ws.transforms_json.read_text())
        mats = [np.asarray(f["transform_matrix"], dtype=np.float64) for f in tf.get("frames", [])]
        c = np.array([m[:3, 3] for m in mats if m.shape == (4, 4)])
        return c if len(c) >= 3 else None
    except (ValueError, KeyError, TypeError):
        log.warning("%s: could not read camera positions; the vertical is taken from the cube alone", ws.transforms_json)
        return None


def run(ws, cfg=None, *, points_path: str | Path | None = None, calibrated: bool | None = None,
                     figure: bool = True) -> dict:
    """Run the traits stage on a workspace; returns the ``traits.json`` content.

    Reads ``WS/export/points.ply`` (or ``points_path``) and ``WS/poses.json`` (``scale_source``
    'aruco' means calibrated), writes ``traits.json``, ``traits.csv`` and ``traits.png``. The height is
    measured from the soil (:func:`plantsplat.traits.checks.workspace_soil`). Measured on a splat, the plant's own
    Gaussians are written to ``plant.ply`` (:func:`write_plant_model`). ``quality`` is ``failed`` when
    nothing could be measured or a check of a stage or of the measurement fails (the files are written
    all the same; the commands then exit with :data:`plantsplat.errors.EXIT_RESULT_FAILED`).

    Usage:
        from plantsplat.workspace import Workspace
        out = run(Workspace("ws/plant_01"))
        out["height_cm"], out["quality"]
    """
    ws = ws if isinstance(ws, Workspace) else Workspace(ws)
    s = cfg if isinstance(cfg, TraitsConfig) else TraitsConfig()
    if points_path:
        ply = Path(points_path)
        if not ply.is_file():
            raise PlantsplatError(f"{ply}: point cloud not found; give an exported points.ply or splat.ply")
        extents = is_splat(ply)  # a splat PLY is read as Gaussians (its opacity is a logit), at any sigma
    elif s.extent_sigma > 0 and (ws.splat_ply.is_file() or not ws.points_ply.is_file()):
        ply, extents = ws.splat_ply, True
        ws.require(ply, "export")
    else:
        ply, extents = ws.points_ply, False
        ws.require(ply, "export")
        if s.extent_sigma > 0:
            log.warning("traits: %s is missing, so the Gaussians' extents are not sampled (centres only, which "
                        "underestimates the traits); re-run `plantsplat export %s`", ws.splat_ply, ws.root)
    if calibrated is None:
        if ws.poses_json.is_file():
            src = read_json(ws.poses_json).get("scale_source", "none")
            calibrated = src == "aruco"
        else:
            raise PlantsplatError(
                f"{ws.poses_json}: missing, so the cloud's scale is unknown; run `plantsplat poses {ws.root}` "
                "or pass --calibrated / --no-calibrated"
            )
    if extents:
        data = read_splat_extent_cloud(ply, s.opacity_min, s.extent_sigma)
        log.info("traits: %s (%d Gaussians%s)", ply, data["gaussians"],
                 f" with their extents at {s.extent_sigma:.2g} sigma" if s.extent_sigma > 0 else ", centres only")
    else:
        data = read_point_cloud(ply, "run `plantsplat export` first or pass --points")
    log.info("traits: %s (%d points, %s)", ply, len(data["xyz"]), "calibrated cm" if calibrated else "unscaled")
    cams = camera_centres(ws)
    soil_z, soil_source, soil_disc, soil_band = workspace_soil(ws, calibrated)
    cube = recorded_cube(ws.markers_json)  # the cube the poses stage measured with
    fruit_report: dict = {}
    own = not points_path  # the frames see the workspace's own model, not a cloud given from elsewhere
    judge = judge_by_views(lambda: fruit_views(ws), s, fruit_report) if s.fruit_views and own else None
    res = measure_traits(data["xyz"], data["rgb"], calibrated=calibrated, opacity=data["opacity"],
                         scales=data["scales"], camera_centres=None if calibrated else cams, settings=s,
                         centre_mask=data.get("centre"), soil_z=soil_z, soil_disc=soil_disc, cube=cube,
                         fruit_judge=judge)
    out = res.to_json()
    if fruit_report:
        out["fruit_pieces"] = fruit_report
    out["input"] = str(ply)
    out["soil_source"] = soil_source
    out["scale"]["calibrated_input"] = bool(calibrated)
    se = None
    if calibrated and ws.poses_json.is_file():
        se = (read_json(ws.poses_json).get("scale_uncertainty") or {}).get("relative_se")
        out["scale"]["standard_error_pct"] = None if se is None else round(100.0 * se, 3)  # the cube's, from poses
    soil = _height_bounds(out, res, soil_z if calibrated else None, soil_disc, se, soil_band)
    _width_bounds(out, res, se)
    _judge(out, res, ws, cams if calibrated else None, soil, cube_edge_cm(s, cube))
    write_json_atomic(ws.traits_json, out)
    write_text_atomic(ws.traits_csv, traits_csv_text(out, ws.root.name))
    write_plant_model(ws, ply if extents else None, data.get("rows"), res)
    if figure and res.plant_points is not None:
        traits_figure(res, ws.traits_png, title=ws.root.name, quality=out["quality"])
    if out["quality"] == "failed":
        log.error("traits: FAILED: %s (details in %s)", "; ".join(out["quality_reasons"][:3]), ws.traits_json)
    for r in out["quality_reasons"] if out["quality"] != "failed" else ():
        log.warning("traits: %s", r)
    for r in res.notes:
        log.info("traits: %s", r)
    return out


def write_plant_model(ws: Workspace, splat: Path | None, rows: np.ndarray | None, res: TraitResult) -> None:
    """``WS/plant.ply``: the Gaussians of the measured ``splat`` whose centres lie on the plant (``rows``: the PLY row of
    each Gaussian the measurement read), every column as the splat has it, so the file opens in the same viewers. Where
    the measurement has no plant Gaussians (a cloud of points, or no plant), an earlier ``plant.ply`` is removed: it
    would describe another result."""
    if splat is None or rows is None or res.plant_gaussians is None or not len(res.plant_gaussians):
        if ws.plant_ply.is_file():
            ws.plant_ply.unlink()
            log.info("traits: removed %s (this measurement found no plant Gaussians)", ws.plant_ply)
        return
    write_splat_rows(ws.plant_ply, splat, rows[res.plant_gaussians])
    log.info("traits: the plant alone, %d of %d Gaussians -> %s", len(res.plant_gaussians), len(rows), ws.plant_ply)


def fruit_views(ws: Workspace) -> list | None:
    """The workspace's frames with their cameras and masks (:func:`plantsplat.train.data.load_scene`; the frames
    without a plant left out), or None where it has none of them."""
    if not ws.masks_dir.is_dir():
        return None
    try:
        return load_scene(ws, need_masks=True, skip_excluded=True).views
    except PlantsplatError as e:
        log.info("traits: the frames cannot be read (%s): fruit pieces are not checked against them", e)
        return None


def _height_bounds(out: dict, res: TraitResult, soil_z: float | None, disc: tuple | None, scale_se: float | None,
                   band_cm: float = 0.0):
    """The soil's interval and the height's bounds (:mod:`plantsplat.traits.height`) into ``out``
    (``soil_interval_cm``, ``height_bounds_cm``); returns the soil interval (None: no pot, or no plant)."""
    P = res.plant_points
    if P is None or not len(P) or out.get("height_cm") is None:
        return None
    soil = None
    if soil_z is not None:  # where it was not seen (a disc), the measurement lowered the rim to the plant's base
        soil = soil_interval(soil_z, disc is None, max(POT_SLAB_CM, band_cm), None if disc is None else res.soil_z,
                             res.base_spread)  # a band of slabs holds the soil; one slab, within half of it
        out["soil_interval_cm"] = [round(soil.low, 3), round(soil.high, 3)]
    lo, hi = height_bounds(float(P[:, 2].max()), soil, scale_se, out.get("height_extent_cm"))
    out["height_bounds_cm"] = [round(lo, 3), round(hi, 3)]
    return soil


def _width_bounds(out: dict, res: TraitResult, scale_se: float | None) -> None:
    """How far the widths' PCA axes can turn and the widths' bounds (:mod:`plantsplat.traits.widths`) into ``out``
    (``width_axis_turn_deg``, ``width1_bounds_cm``, ``width2_bounds_cm``)."""
    P = res.plant_points
    if P is None or len(P) < 3 or out.get("width1_cm") is None:
        return
    turn = axis_turn_deg(P, MeasureConfig().even_cell_cm)
    k = res.settings.get("extent_sigma") or 0.0
    inner, outer = footprint_range(P, res.plant_centres, k) if res.plant_centres is not None and k > 0 else (None, None)
    (lo1, hi1), (lo2, hi2) = width_bounds(P, turn, scale_se, inner=inner, outer=outer)
    out["width_axis_turn_deg"] = round(turn, 1)
    out["width1_bounds_cm"] = [round(lo1, 3), round(hi1, 3)]
    out["width2_bounds_cm"] = [round(lo2, 3), round(hi2, 3)]


def _decided_top(ws) -> float | None:
    """The top of the plant the segment stage decided in its quick model (cm, cube frame; ``segment.json``), or None."""
    if not ws.segment_json.is_file():
        return None
    return (((read_json(ws.segment_json).get("capture") or {}).get("object") or {}).get("plant_top_cm"))


def _judge(out: dict, res: TraitResult, ws, cams: np.ndarray | None, soil, cube_cm: float) -> None:
    """Every stage's checks and the measurement's own (:mod:`plantsplat.traits.checks`) into ``out``'s ``checks``,
    ``quality`` and ``quality_reasons``."""
    checks = stage_checks(ws)
    if res.plant_points is not None:
        top = float(res.plant_points[:, 2].max())
        checks += result_checks(res.traits, len(res.plant_points), top if cams is not None else None,
                                None if cams is None else float(cams[:, 2].max()), cube_cm,
                                height_bounds=out.get("height_bounds_cm"), soil=soil,
                                width_bounds=(out.get("width1_bounds_cm"), out.get("width2_bounds_cm")),
                                width_turn_deg=out.get("width_axis_turn_deg"),
                                decided_top_cm=_decided_top(ws) if cams is not None else None)
    out["checks"] = [c.as_dict() for c in checks]
    verdict = quality(checks)
    order = ["ok", "warning", "failed"]
    out["quality"] = max(res.quality, verdict, key=order.index)
    out["quality_reasons"] = [f"check {c.line()}" for c in checks if not c.passed] + list(res.reasons)

"""Many plants: a manifest of videos, one workspace per plant, run in local worker processes or as Ray tasks.

Manifest (CSV): a ``plant_id`` column and an ``input`` column (a video or an image folder; relative
paths are relative to the manifest). Each plant runs the whole pipeline in ``OUT/plants/<plant_id>/``;
one plant's failure is recorded and does not stop the others, and re-running resumes each plant
where it stopped (finished plants are skipped stage by stage).

Outputs in ``OUT/``: ``traits.csv`` (one row per plant, with status and error), ``batch.json`` (per
plant status, reason, time), and with ground truth ``accuracy.json`` / ``accuracy.csv`` (the paper's
R2, RMSE, MAPE, MAE, Acc per trait) and scatter plots.

Usage:
    summary = run_batch("plants.csv", "out", BatchConfig(workers=2))
"""

from __future__ import annotations

import csv
import dataclasses
import io
import multiprocessing as mp
import os
import re
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro

from plantsplat.errors import PlantsplatError
from plantsplat.groundtruth import read_ground_truth_csv
from plantsplat.io import csv_cell, write_json_atomic, write_text_atomic
from plantsplat.log import get_logger, progress, setup_logging
from plantsplat.options import check_run_options
from plantsplat.pipeline import RunConfig, run_pipeline
from plantsplat.preflight import check_option_paths, check_workspace_folder
from plantsplat.traitdefs import TRAIT_KEYS

log = get_logger(__name__)

PLANTS_PER_PROCESS = 1
"""Plants one worker process runs before it is replaced: one, so that each plant's result is the one a single
`plantsplat run` gives (a second plant run in the same process was measured to come out differently)."""

_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


@dataclass
class ManifestRow:
    plant_id: str
    input: Path | None
    problem: str | None = None


def read_manifest(path: str | Path) -> list[ManifestRow]:
    """Read a manifest CSV; rows with a problem (missing file, duplicate or bad id) carry ``problem``."""
    path = Path(path)
    if not path.is_file():
        raise PlantsplatError(f"{path}: manifest not found")
    try:
        text = path.read_text(encoding="utf-8-sig")
        reader = csv.DictReader(io.StringIO(text))
        header = [h.strip() for h in (reader.fieldnames or [])]
        raw_rows = list(reader)
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise PlantsplatError(f"{path}: unreadable CSV ({exc})") from exc
    if "plant_id" not in header or "input" not in header:
        raise PlantsplatError(f"{path}: the manifest needs the columns plant_id and input (a video or image folder)")
    rows: list[ManifestRow] = []
    seen: set[str] = set()
    for lineno, raw in enumerate(raw_rows, start=2):
        r = {(k or "").strip(): (v or "").strip() for k, v in raw.items()}
        pid, inp = r.get("plant_id", ""), r.get("input", "")
        if not pid:
            rows.append(ManifestRow(f"<line {lineno}>", None, f"{path}:{lineno}: no plant_id"))
            continue
        if not _ID_RE.match(pid):
            rows.append(ManifestRow(pid, None, f"{path}:{lineno}: plant_id {pid!r} must be letters, digits, '.', '_' or '-'"))
            continue
        if pid in seen:
            rows.append(ManifestRow(pid, None, f"{path}:{lineno}: duplicate plant_id {pid!r} (first row kept)"))
            continue
        seen.add(pid)
        if not inp:
            rows.append(ManifestRow(pid, None, f"{path}:{lineno}: no input for plant {pid!r}"))
            continue
        p = Path(inp)
        if not p.is_absolute():
            p = (path.parent / p).resolve()
        if not p.exists():
            rows.append(ManifestRow(pid, p, f"{p}: input of plant {pid!r} not found"))
            continue
        rows.append(ManifestRow(pid, p))
    if not rows:
        raise PlantsplatError(f"{path}: the manifest lists no plants")
    return rows


@dataclass
class BatchConfig:
    workers: int = 1
    """Plants processed at once on this machine (worker processes); CPU threads are shared out among them."""
    ray_address: str | None = None
    """Run plants as Ray tasks on this cluster (`auto` for a running cluster, `local` to start one here)."""
    ground_truth: Path | None = None
    """CSV of measured traits (plant_id + trait columns) for the accuracy table."""
    run: Annotated[RunConfig, tyro.conf.arg(name="")] = field(default_factory=RunConfig)
    """Every stage's options, as for `plantsplat run`."""


def _threads_for(workers: int) -> int:
    return max(1, (os.cpu_count() or 1) // max(1, workers))


def _limit_threads(n: int) -> None:
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS"):
        os.environ[var] = str(n)
    os.environ.setdefault("PLANTSPLAT_NO_PROGRESS", "1")
    try:
        import torch  # deferred: heavy, and only a worker process needs its threads set

        torch.set_num_threads(n)
    except Exception:
        pass


def run_one_plant(plant_id: str, source: str, ws: str, run_cfg: RunConfig, threads: int) -> dict:
    """Run the whole pipeline for one plant; never raises (the result carries the failure)."""
    _limit_threads(threads)
    setup_logging(quiet=True)
    opts = dataclasses.replace(run_cfg, plant_id=plant_id)
    if opts.ground_truth is not None:

        rows, _ = read_ground_truth_csv(opts.ground_truth)
        if plant_id not in rows:
            opts = dataclasses.replace(opts, ground_truth=None)  # no usable truth for this plant: nothing to evaluate
    t0 = time.perf_counter()
    try:
        summary = run_pipeline(Path(source), Path(ws), opts)
        traits = summary.get("traits", {})
        failed = traits.get("quality") == "failed"  # measured, but a check failed: the numbers must not be used
        return {"plant_id": plant_id, "status": "failed" if failed else "ok", "traits": traits,
                "error": "; ".join(traits.get("quality_reasons", [])[:3]) if failed else "",
                "seconds": round(time.perf_counter() - t0, 2), "workspace": ws}
    except PlantsplatError as exc:
        return {"plant_id": plant_id, "status": "failed", "error": str(exc),
                "seconds": round(time.perf_counter() - t0, 2), "workspace": ws}
    except Exception as exc:  # a bug must not stop the other plants either
        return {"plant_id": plant_id, "status": "failed", "error": f"{type(exc).__name__}: {exc}",
                "seconds": round(time.perf_counter() - t0, 2), "workspace": ws}


def _run_local(jobs: list[tuple], workers: int) -> list[dict]:
    """The plants on this machine, ``workers`` at a time; their results in the order they finish."""
    threads = _threads_for(workers)
    results = []
    # every plant in a fresh process, as `plantsplat run` would run it: a process that has run one plant's stages
    # carries state into the next (the demo's width 2 came out 1.7 % apart on a second run in one process)
    with ProcessPoolExecutor(max_workers=max(1, workers), mp_context=mp.get_context("spawn"),
                             max_tasks_per_child=PLANTS_PER_PROCESS) as pool:
        futures = [pool.submit(run_one_plant, *job, threads) for job in jobs]
        for fut in progress(as_completed(futures), "plants", total=len(futures)):
            res = fut.result()
            log.info("plant %s: %s (%.0f s)", res["plant_id"], res["status"], res["seconds"])
            results.append(res)
    return results


def _run_ray(jobs: list[tuple], address: str, run_cfg: RunConfig, workers: int) -> list[dict]:
    try:
        import ray  # deferred: optional (the cluster backend)
    except ImportError as exc:
        raise PlantsplatError("--ray-address needs Ray: pip install 'plantsplat[ray]'") from exc

    init_kwargs = {"ignore_reinit_error": True, "log_to_driver": False, "include_dashboard": False}
    if address == "local":
        init_kwargs["num_cpus"] = os.cpu_count()
    else:
        init_kwargs["address"] = address
    try:
        ray.init(**init_kwargs)
    except Exception as exc:
        raise PlantsplatError(f"Ray cluster {address!r}: cannot connect ({exc})") from exc
    cpus = int(ray.cluster_resources().get("CPU", 1))
    per_task = max(1, cpus // max(1, workers)) if workers > 1 else max(1, cpus)
    gpus = 1 if run_cfg.train.backend == "gsplat" else 0
    remote = ray.remote(num_cpus=per_task, num_gpus=gpus, max_retries=0, max_calls=PLANTS_PER_PROCESS)(run_one_plant)
    refs = [remote.remote(*job, per_task) for job in jobs]
    results = []
    pending = list(refs)
    try:
        for _ in progress(range(len(refs)), "plants (ray)"):
            done, pending = ray.wait(pending, num_returns=1)
            try:
                results.append(ray.get(done[0]))
            except Exception as exc:  # a crashed worker: name the plant
                idx = refs.index(done[0])
                results.append({"plant_id": jobs[idx][0], "status": "failed", "error": f"Ray task failed: {exc}"})
    finally:
        if address == "local":
            ray.shutdown()  # the cluster was started for this batch
    return results


def run_batch(manifest: str | Path, out: str | Path, opts: BatchConfig) -> dict:
    """Run every plant of ``manifest`` into ``out``; returns the batch summary (also ``out/batch.json``)."""

    out = Path(out)
    check_workspace_folder(out)
    check_option_paths(dataclasses.replace(opts.run, ground_truth=opts.ground_truth))
    check_run_options(opts.run)
    out.mkdir(parents=True, exist_ok=True)
    rows = read_manifest(manifest)
    if opts.ground_truth is not None:

        read_ground_truth_csv(opts.ground_truth)  # an unreadable file stops the batch before any work
    run_cfg = dataclasses.replace(opts.run, ground_truth=opts.ground_truth)
    jobs = [
        (r.plant_id, str(r.input), str(out / "plants" / r.plant_id), run_cfg)
        for r in rows
        if r.problem is None
    ]
    t0 = time.perf_counter()
    if opts.ray_address:
        results = _run_ray(jobs, opts.ray_address, opts.run, opts.workers)
    else:
        results = _run_local(jobs, opts.workers)
    wall = time.perf_counter() - t0
    by_id = {r["plant_id"]: r for r in results}
    plants = []
    for r in rows:
        if r.problem is not None:
            plants.append({"plant_id": r.plant_id, "status": "skipped", "error": r.problem})
        else:
            plants.append(by_id.get(r.plant_id, {"plant_id": r.plant_id, "status": "failed", "error": "no result"}))
    summary = {
        "manifest": str(manifest),
        "plants": plants,
        "n_ok": sum(p["status"] == "ok" for p in plants),
        "n_failed": sum(p["status"] != "ok" for p in plants),
        "wall_seconds": round(wall, 2),
        "workers": opts.workers,
        "ray_address": opts.ray_address,
    }
    _write_traits_csv(out / "traits.csv", plants)
    if opts.ground_truth is not None:
        summary["accuracy"] = _accuracy(out, plants, opts.ground_truth)
    write_json_atomic(out / "batch.json", summary)
    truth = None
    if opts.ground_truth is not None:

        truth, _ = read_ground_truth_csv(opts.ground_truth)
    if opts.run.report:  # --no-report: neither the plants' reports nor the batch's
        _maybe_batch_report(out, plants, summary.get("accuracy"), truth)
    return summary


def _write_traits_csv(path: Path, plants: list[dict]) -> None:
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["plant_id", "status", *TRAIT_KEYS, "quality", "scale_source", "error"])
    for p in plants:
        t = p.get("traits") or {}
        w.writerow(
            [csv_cell(p["plant_id"]), p["status"], *[_fmt(t.get(k)) for k in TRAIT_KEYS], t.get("quality", ""),
             t.get("scale_source", ""), csv_cell(p.get("error", ""))]
        )
    write_text_atomic(path, buf.getvalue())


def _fmt(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.3f}"
    return str(v)


def _accuracy(out: Path, plants: list[dict], gt_path: Path) -> dict:
    from plantsplat.traits.stats import accuracy_table, scatter_plots  # deferred: it loads matplotlib

    truth, problems = read_ground_truth_csv(gt_path)
    for p in problems:
        log.warning("ground truth: %s", p)
    estimates: dict[str, dict[str, float]] = {}
    for p in plants:
        if p["status"] == "ok" and p["plant_id"] in truth:
            estimates[p["plant_id"]] = p.get("traits") or {}
    missing = [p["plant_id"] for p in plants if p["status"] == "ok" and p["plant_id"] not in truth]
    traits = [t for t in TRAIT_KEYS if any(t in v for v in truth.values())]
    table = accuracy_table(estimates, truth, traits)
    write_json_atomic(out / "accuracy.json", {"table": table, "ground_truth_problems": problems,
                                              "plants_without_ground_truth": missing})
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["trait", "n", "R2", "RMSE", "MAPE_pct", "MAE", "Acc_pct"])
    for t, m in table.items():
        w.writerow([t, m.get("n"), _fmt(m.get("r2")), _fmt(m.get("rmse")), _fmt(m.get("mape")), _fmt(m.get("mae")),
                    _fmt(m.get("acc"))])
    write_text_atomic(out / "accuracy.csv", buf.getvalue())
    scatter_plots(estimates, truth, traits, out / "scatter.png")
    return {"table": table, "ground_truth_problems": problems, "plants_without_ground_truth": missing}


def _maybe_batch_report(out: Path, plants: list[dict], accuracy: dict | None, truth: dict | None) -> None:
    try:
        from plantsplat.report.batch import write_batch_report  # deferred: it loads OpenCV (only with a report)
    except ImportError:
        return
    reports = {p["plant_id"]: Path(p["workspace"]) / "report.html" for p in plants
               if p.get("workspace") and (Path(p["workspace"]) / "report.html").exists()}
    rows = [{"plant_id": p["plant_id"], "status": p["status"], "error": p.get("error"), **(p.get("traits") or {})}
            for p in plants]
    write_batch_report(out, rows, accuracy, reports, truth=truth)

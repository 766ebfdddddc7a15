"""`plantsplat batch`: many plants from a manifest, locally in parallel or on a Ray cluster."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro
from rich.table import Table

from plantsplat.batch import BatchConfig, run_batch
from plantsplat.commands import Command
from plantsplat.errors import EXIT_RESULT_FAILED
from plantsplat.log import console


@dataclass
class BatchCommand:
    """Run every plant listed in MANIFEST.csv (columns plant_id, input) into OUT/plants/<plant_id>/.

    One plant's failure does not stop the others; re-running resumes. Writes OUT/traits.csv and,
    with --ground-truth, the paper's accuracy table (R2, RMSE, MAPE, MAE, Acc) and scatter plots.
    Exit code 0 only when every plant succeeded; 4 when the only failures are results that failed their
    checks (marked failed in traits.csv), 1 when a plant could not be processed at all.
    Example: plantsplat batch plants.csv --out experiment1 --workers 2 --ground-truth measured.csv
    """

    manifest: tyro.conf.Positional[Path]
    """CSV with columns plant_id and input (a video or image folder; relative to the manifest)."""
    out: Path
    """Folder for the per-plant workspaces and the batch tables."""
    batch: Annotated[BatchConfig, tyro.conf.arg(name="")] = field(default_factory=BatchConfig)


def run(cfg: BatchCommand) -> int:
    summary = run_batch(cfg.manifest, cfg.out, cfg.batch)
    for p in summary["plants"]:
        status = p["status"]
        colour = "green" if status == "ok" else "red"
        console.print(f"[{colour}]{status:8s}[/] {p['plant_id']}" + (f": {p['error']}" if p.get("error") else ""))
    console.print(f"{summary['n_ok']} of {len(summary['plants'])} plants succeeded; traits: {cfg.out / 'traits.csv'}")
    acc = summary.get("accuracy")
    if acc:
        t = Table(title="Accuracy against ground truth")
        for col in ("trait", "n", "R2", "RMSE", "MAPE %", "MAE", "Acc %"):
            t.add_column(col, justify="right")
        for trait, m in acc["table"].items():
            t.add_row(trait, str(m.get("n")), *[
                "—" if m.get(k) is None else f"{m[k]:.3f}" for k in ("r2", "rmse", "mape", "mae", "acc")
            ])
        console.print(t)
    return batch_exit_code(summary)


def batch_exit_code(summary: dict) -> int:
    """The batch's exit code: 0 when every plant succeeded; 4 (a failed result) when the only failures are results that
    failed their checks, every file written; else 1 (a plant's run failed, or one was skipped).

    Example:
        >>> batch_exit_code({"n_failed": 1, "plants": [{"status": "ok"}, {"status": "failed",
        ...                                                               "traits": {"quality": "failed"}}]})
        4
    """
    if summary["n_failed"] == 0:
        return 0
    results = {p["status"] for p in summary["plants"]}
    return EXIT_RESULT_FAILED if all(p["status"] == "ok" or (p.get("traits") or {}).get("quality") == "failed"
                                     for p in summary["plants"]) and "failed" in results else 1


COMMAND = Command(name="batch", config=BatchCommand, run=run, help="Many plants from a manifest (local or Ray).", order=80)

"""The batch report: traits of every plant, accuracy against hand measurements, interactive scatter plots.

One self-contained ``report.html`` (plotly.js inlined from the installed ``plotly`` package, no CDN)
with links to each plant's own report.

Usage:
    rows = [{"plant_id": "p1", "status": "ok", "height_cm": 20.1}, {"plant_id": "p2", "status": "ok", "height_cm": 25.3}]
    truth = {"p1": {"height_cm": 20.0}, "p2": {"height_cm": 26.0}}
    write_batch_report("out", rows, None, {"p1": "out/plants/p1/report.html"}, truth=truth)
"""

from __future__ import annotations

import datetime as _dt
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from plantsplat.errors import PlantsplatError
from plantsplat.io import write_text_atomic
from plantsplat.log import get_logger
from plantsplat.report import html as H
from plantsplat.traitdefs import TRAIT_KEYS, TRAIT_UNITS

log = get_logger(__name__)

ID_KEYS = ("plant_id", "id", "plant", "name")
METRIC_COLUMNS = [("n", "n"), ("r2", "R²"), ("rmse", "RMSE"), ("mape", "MAPE (%)"), ("mae", "MAE"),
                  ("acc", "Acc (%)"), ("bias", "bias"), ("slope", "slope"), ("intercept", "intercept"),
                  ("missing", "missing")]


def _plant_id(row: Mapping[str, Any], i: int) -> str:
    for k in ID_KEYS:
        if row.get(k) not in (None, ""):
            return str(row[k])
    return f"plant {i + 1}"


def _number(v: Any) -> float | None:
    if H.is_number(v) and math.isfinite(float(v)):
        return float(v)
    return None


def _truth_from_rows(rows: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, float]]:
    """Ground truth carried in the rows as ``<trait>_gt`` or ``gt_<trait>`` columns."""
    truth: dict[str, dict[str, float]] = {}
    for i, r in enumerate(rows):
        for t in TRAIT_KEYS:
            for k in (f"{t}_gt", f"gt_{t}"):
                v = _number(r.get(k))
                if v is not None:
                    truth.setdefault(_plant_id(r, i), {})[t] = v
    return truth


def _accuracy_table(accuracy: Mapping[str, Any] | None) -> Mapping[str, Mapping[str, Any]] | None:
    """``{trait: {metric: value}}`` from either that mapping itself or ``{"table": ...}`` around it."""
    if not accuracy:
        return None
    table = accuracy.get("table", accuracy)
    if not isinstance(table, Mapping):
        return None
    table = {k: v for k, v in table.items() if isinstance(v, Mapping)}
    return table or None


def _table_from_truth(rows: Sequence[Mapping[str, Any]], truth: Mapping[str, Mapping[str, float]]):
    """The accuracy table computed here (plantsplat.traits.stats) when only per-plant truth was given."""
    try:
        from plantsplat.traits.stats import accuracy_table  # deferred: matplotlib and SciPy; no table without them
    except ImportError:
        return None
    est = {_plant_id(r, i): {t: _number(r.get(t)) for t in TRAIT_KEYS} for i, r in enumerate(rows)}
    traits = [t for t in TRAIT_KEYS if any(t in v for v in truth.values())]
    table = accuracy_table({k: v for k, v in est.items() if k in truth}, dict(truth), traits)
    return {t: m for t, m in table.items() if m.get("n")} or None


def _scatter_html(rows: Sequence[Mapping[str, Any]], truth: Mapping[str, Mapping[str, Any]],
                  table: Mapping[str, Mapping[str, Any]] | None) -> tuple[str, int]:
    """One interactive plotly scatter (estimate vs hand measurement, 1:1 line) per trait with data."""
    import plotly.graph_objects as go  # deferred: plotly is slow to load, and only plots need it

    est = {_plant_id(r, i): r for i, r in enumerate(rows)}
    divs = []
    for t in TRAIT_KEYS:
        pts = [(pid, _number(truth[pid].get(t)), _number(est[pid].get(t))) for pid in truth if pid in est]
        pts = [(p, y, yh) for p, y, yh in pts if y is not None and yh is not None]
        if not pts:
            continue
        ids, y, yh = zip(*pts)
        lo, hi = min(min(y), min(yh)), max(max(y), max(yh))
        pad = 0.05 * (hi - lo or 1.0)
        unit = TRAIT_UNITS.get(t, "")
        fig = go.Figure()
        fig.add_trace(go.Scatter(x=[lo - pad, hi + pad], y=[lo - pad, hi + pad], mode="lines", name="1:1",
                                 line={"dash": "dash", "color": "#888"}, hoverinfo="skip"))
        fig.add_trace(go.Scatter(x=list(y), y=list(yh), mode="markers", name="plants", text=list(ids),
                                 marker={"size": 9, "color": "#2e7d32"},
                                 hovertemplate="%{text}<br>measured %{x:.2f}<br>estimated %{y:.2f}<extra></extra>"))
        m = (table or {}).get(t, {})
        sub = ""
        if m:
            bits = [f"{lab} {H.fmt_value(m[k])}" for k, lab in METRIC_COLUMNS[:6] if k in m and k != "n"]
            sub = "<br><sup>" + ", ".join(bits).replace("&ndash;", "-") + "</sup>"
        fig.update_layout(title={"text": f"{t}{sub}"}, width=420, height=400, margin={"l": 50, "r": 10, "t": 60, "b": 45},
                          xaxis_title=f"hand measurement ({unit})" if unit else "hand measurement",
                          yaxis_title=f"plantsplat estimate ({unit})" if unit else "plantsplat estimate",
                          showlegend=False, template="plotly_white")
        fig.update_yaxes(scaleanchor="x", scaleratio=1)
        divs.append(f'<div class="scatter" data-trait="{H.esc(t)}" style="display:inline-block">'
                    + fig.to_html(full_html=False, include_plotlyjs=False, config={"displaylogo": False}) + "</div>")
    return "".join(divs), len(divs)


def write_batch_report(
    out_dir: str | os.PathLike,
    traits_rows: list[dict],
    accuracy: dict | None,
    plant_reports: Mapping[str, str | os.PathLike],
    truth: Mapping[str, Mapping[str, float]] | None = None,
) -> Path:
    """Write ``out_dir/report.html`` for a batch of plants.

    Args:
        traits_rows: one dict per plant: an id (``plant_id``), optional ``status`` / ``error``, and the
            trait values (``height_cm``, ...). Ground truth may ride along as ``<trait>_gt`` columns.
        accuracy: ``{trait: {n, r2, rmse, mape, mae, acc, ...}}`` or ``{"table": that, ...}`` (as written by
            ``plantsplat batch``), or None without ground truth.
        plant_reports: plant id -> path of that plant's ``report.html`` (linked relative to ``out_dir``).
        truth: ``{plant_id: {trait: hand measurement}}`` for the scatter plots (also read from
            ``accuracy["truth"]`` when given there).

    Usage:
        write_batch_report("runs/batch", rows, acc, {"p1": "runs/batch/plants/p1/report.html"})
    """
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise PlantsplatError(f"{out_dir}: exists and is not a folder; choose another output folder", exit_code=2)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = [dict(r) for r in traits_rows]
    table = _accuracy_table(accuracy)
    truth_all: dict[str, dict[str, float]] = {k: dict(v) for k, v in (truth or {}).items()}
    if accuracy and isinstance(accuracy.get("truth"), Mapping):
        for k, v in accuracy["truth"].items():
            truth_all.setdefault(str(k), {}).update(v)
    for k, v in _truth_from_rows(rows).items():
        truth_all.setdefault(k, {}).update(v)
    if table is None and truth_all:
        table = _table_from_truth(rows, truth_all)

    # traits table, with a link to each plant's report
    links = {}
    for pid, p in plant_reports.items():
        rel = os.path.relpath(Path(p).resolve(), out_dir.resolve())
        links[str(pid)] = f'<a href="{H.esc(Path(rel).as_posix())}">{H.esc(pid)}</a>'
    trait_cols = [t for t in TRAIT_KEYS if any(t in r for r in rows)]
    other = []
    for r in rows:
        other += [k for k in r if k not in other and k not in trait_cols and k not in ID_KEYS and k != "error"
                  and not k.endswith("_gt") and not k.startswith("gt_") and not isinstance(r[k], (dict, list))]
    table_rows = []
    for i, r in enumerate(rows):
        pid = _plant_id(r, i)
        table_rows.append({"plant": links.get(pid, H.esc(pid)), **r, "error": r.get("error")})
    cols = ["plant", *trait_cols, *other, "error"]
    labels = {t: f"{t}" for t in trait_cols}
    traits_html = H.rows_table(table_rows, cols, labels=labels, raw_html_columns=("plant",))
    n_ok = sum(1 for r in rows if r.get("status", "ok") == "ok")
    sections = [H.section("traits", f"Traits of {len(rows)} plants ({n_ok} measured)", traits_html)]

    if table:
        acc_rows = [{"trait": t, **m} for t, m in table.items()]
        present = [(k, lab) for k, lab in METRIC_COLUMNS if any(k in m for m in table.values())]
        acc_html = H.rows_table(acc_rows, ["trait", *[k for k, _ in present]], labels=dict(present))
        extra = {k: v for k, v in (accuracy or {}).items() if k not in {"table", "truth"} and v}
        if extra:
            acc_html += "<details><summary>ground-truth notes</summary>" + H.generic_tables(
                {k: (v if isinstance(v, Mapping) else {"": v}) for k, v in extra.items()}) + "</details>"
        sections.append(H.section("accuracy", "Accuracy against hand measurements", acc_html))
    else:
        sections.append(H.section("accuracy", "Accuracy against hand measurements", H.missing_note(
            "accuracy table (no ground truth given)", "pass --ground-truth measurements.csv to `plantsplat batch`")))

    head_extra = ""
    if truth_all:
        try:
            import plotly.offline  # deferred: without plotly the report says how to get its plots
        except ImportError:
            plots_html = H.missing_note("interactive scatter plots", "install plotly: pip install plotly")
        else:
            plots_html, n_plots = _scatter_html(rows, truth_all, table)
            if n_plots:
                head_extra = H.inline_script(plotly.offline.get_plotlyjs())
            else:
                plots_html = H.missing_note("scatter plots (no plant has both an estimate and a measurement)",
                                            "check that plant ids match between the manifest and the ground truth")
    else:
        plots_html = H.missing_note("scatter plots (no per-plant hand measurements given)",
                                    "pass truth={plant_id: {trait: value}} or <trait>_gt columns")
    sections.append(H.section("scatter", "Estimates against hand measurements", plots_html))

    when = _dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    header = (f"<header><h1>plantsplat batch report</h1><div class=\"sub\">{H.esc(str(out_dir.resolve()))} · "
              f"{len(rows)} plants · generated {H.esc(when)}</div></header>")
    text = H.page("plantsplat batch report", header + "<main>" + "".join(sections) + "</main>", head_extra)
    path = out_dir / "report.html"
    write_text_atomic(path, text)
    log.info("batch report: %s (%.1f MB)", path, len(text.encode()) / 1e6)
    return path

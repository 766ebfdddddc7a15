"""Accuracy statistics of trait estimates against ground truth, exactly as the paper defines them.

With ``y_i`` the true value, ``y_hat_i`` the estimate and ``N`` plants (paper, section 2.5):

* ``R2   = 1 - sum (y_i - y_hat_i)^2 / sum (y_i - mean(y))^2`` (coefficient of determination of the
  estimates themselves, not of a fitted line; it can be negative);
* ``RMSE = sqrt(mean (y_i - y_hat_i)^2)``;
* ``MAPE = mean |(y_i - y_hat_i) / y_i| * 100 %``;
* ``MAE  = mean |y_i - y_hat_i|``;
* ``Acc  = 1 - MAPE`` (in percent: ``100 % - MAPE``).

Example:
    >>> m = trait_metrics([10.0, 20.0, 30.0], [11.0, 19.0, 30.0])
    >>> round(m["r2"], 3), round(m["rmse"], 3), round(m["mape"], 3), round(m["acc"], 3)
    (0.99, 0.816, 5.0, 95.0)
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np

from plantsplat.io import atomic_path
from plantsplat.traitdefs import TRAIT_LABELS, TRAIT_UNITS

PANEL_SIZE_IN = 4.3
"""Width and height of one trait's panel in :func:`scatter_plots` (inches)."""
PLOT_DPI = 110
"""Resolution of the scatter plots' PNG (dots per inch)."""
PLOT_PAD = 0.08
"""The axes reach this share of the data's range beyond it on each side."""
MARKER_AREA = 28
"""Area of one plant's marker (points squared)."""
IDEAL_LINE_WIDTH = 1.2
"""Width of the dashed y = x line (points)."""
FIT_LINE_WIDTH = 1.5
"""Width of the fitted line (points)."""
STATS_CORNER = (0.04, 0.96)
"""Where the panel's R2 / RMSE / MAPE text starts (axes fraction, top left)."""
STATS_FONT_SIZE = 9
"""Font size of the panel's R2 / RMSE / MAPE text."""
LEGEND_FONT_SIZE = 8
"""Font size of the legends."""
GRID_ALPHA = 0.3
"""Opacity of the grid lines."""


def _pair(truth, estimate) -> tuple[np.ndarray, np.ndarray]:
    y = np.asarray(truth, dtype=np.float64).reshape(-1)
    yh = np.asarray(estimate, dtype=np.float64).reshape(-1)
    if y.shape != yh.shape:
        raise ValueError(f"truth and estimate differ in length: {y.shape} vs {yh.shape}")
    return y, yh


def r2(truth, estimate) -> float:
    """Coefficient of determination ``1 - SS_res / SS_tot`` (nan when all truths are equal)."""
    y, yh = _pair(truth, estimate)
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    if ss_tot == 0:
        return float("nan")
    return 1.0 - float(np.sum((y - yh) ** 2)) / ss_tot


def rmse(truth, estimate) -> float:
    """Root mean squared error (units of the trait)."""
    y, yh = _pair(truth, estimate)
    return float(np.sqrt(np.mean((y - yh) ** 2)))


def mape(truth, estimate) -> float:
    """Mean absolute percentage error, in percent. Truths equal to 0 are an error (undefined)."""
    y, yh = _pair(truth, estimate)
    if np.any(y == 0):
        raise ValueError("MAPE is undefined when a true value is 0")
    return float(np.mean(np.abs((y - yh) / y)) * 100.0)


def mae(truth, estimate) -> float:
    """Mean absolute error (units of the trait)."""
    y, yh = _pair(truth, estimate)
    return float(np.mean(np.abs(y - yh)))


def accuracy(truth, estimate) -> float:
    """``Acc = 1 - MAPE``, in percent."""
    return 100.0 - mape(truth, estimate)


def fitted_line(truth, estimate) -> tuple[float, float]:
    """Least-squares line ``estimate = slope * truth + intercept`` (the paper's red fitted line)."""
    y, yh = _pair(truth, estimate)
    if len(y) < 2 or np.ptp(y) == 0:
        return float("nan"), float("nan")
    slope, intercept = np.polyfit(y, yh, 1)
    return float(slope), float(intercept)


def trait_metrics(truth, estimate) -> dict[str, float]:
    """All metrics of one trait: ``n, r2, rmse, mape, mae, acc, bias, slope, intercept``.

    ``mape`` and ``acc`` are in percent; ``rmse``, ``mae`` and ``bias`` (mean estimate - truth) in the
    trait's units; ``slope`` and ``intercept`` are the fitted line ``estimate = slope * truth + intercept``.
    """
    y, yh = _pair(truth, estimate)
    ok = np.isfinite(y) & np.isfinite(yh)
    y, yh = y[ok], yh[ok]
    if len(y) == 0:
        return {"n": 0}
    slope, intercept = fitted_line(y, yh)
    has_zero = bool(np.any(y == 0))
    return {
        "n": int(len(y)),
        "r2": r2(y, yh),
        "rmse": rmse(y, yh),
        "mape": float("nan") if has_zero else mape(y, yh),
        "mae": mae(y, yh),
        "acc": float("nan") if has_zero else accuracy(y, yh),
        "bias": float(np.mean(yh - y)),
        "slope": slope,
        "intercept": intercept,
    }


def _value(v) -> float:
    try:
        return float("nan") if v is None else float(v)
    except (TypeError, ValueError):
        return float("nan")


def _align(estimates, truths, key: str) -> tuple[np.ndarray, np.ndarray]:
    """``(truth [N], estimate [N])`` for one trait from any of the accepted layouts.

    Layouts: per-plant mappings keyed by plant id (``{id: {trait: value}}``, aligned by id over the
    truths' plants), sequences of per-plant dicts (aligned by position), or per-trait sequences
    (``{trait: [values]}``).
    """
    per_plant = isinstance(truths, Mapping) and truths and all(isinstance(v, Mapping) for v in truths.values())
    if per_plant:
        if not isinstance(estimates, Mapping):
            raise ValueError("truths are keyed by plant id, so estimates must be too")
        ids = list(truths)
        y = np.array([_value(truths[i].get(key)) for i in ids])
        yh = np.array([_value((estimates.get(i) or {}).get(key)) for i in ids])
        return y, yh
    if isinstance(truths, Mapping):
        y = np.asarray(truths[key], dtype=np.float64)
        yh = np.asarray(estimates[key], dtype=np.float64)
    else:
        y = np.array([_value(r.get(key)) for r in truths])
        yh = np.array([_value(r.get(key)) for r in estimates])
    if y.shape != yh.shape:
        raise ValueError(f"{key}: {len(yh)} estimates but {len(y)} truths")
    return y, yh


def accuracy_table(
    estimates: Sequence[Mapping] | Mapping[str, Sequence[float]],
    truths: Sequence[Mapping] | Mapping[str, Sequence[float]],
    traits: Sequence[str] = ("height_cm", "width1_cm", "width2_cm"),
) -> dict[str, dict[str, float]]:
    """Metrics per trait over many plants.

    ``estimates`` and ``truths`` are dicts keyed by plant id (``{id: {trait: value}}``; the truths'
    plants are evaluated), sequences of per-plant dicts (``traits.json`` and ``ground_truth.json``
    contents, same order) or dicts of per-trait sequences. Plants whose estimate is missing (absent,
    None, a failed measurement) are left out of that trait's metrics and counted in ``missing``;
    plants without a truth are ignored. Metric keys: see :func:`trait_metrics`.

    Example:
        >>> est = [{"height_cm": 10.5}, {"height_cm": 19.0}, {"height_cm": None}]
        >>> gt = [{"height_cm": 10.0}, {"height_cm": 20.0}, {"height_cm": 15.0}]
        >>> t = accuracy_table(est, gt, ["height_cm"])
        >>> t["height_cm"]["n"], t["height_cm"]["missing"], round(t["height_cm"]["mape"], 2)
        (2, 1, 5.0)
        >>> t = accuracy_table({"p1": {"height_cm": 9.0}}, {"p1": {"height_cm": 10.0}, "p2": {"height_cm": 12.0}})
        >>> t["height_cm"]["n"], t["height_cm"]["missing"], round(t["height_cm"]["mae"], 2)
        (1, 1, 1.0)
    """
    out = {}
    for key in traits:
        y, yh = _align(estimates, truths, key)
        m = trait_metrics(y, yh)
        m["missing"] = int(np.sum(np.isfinite(y) & ~np.isfinite(yh)))
        out[key] = m
    return out


def format_table(table: Mapping[str, Mapping[str, float]], fmt: str = "markdown") -> str:
    """The paper's table (rows = traits; R2, RMSE, MAPE, MAE, Acc) as Markdown or LaTeX."""
    head = ["", "R2", "RMSE", "MAPE", "MAE", "Acc", "n"]
    rows = []
    for key, m in table.items():
        unit = TRAIT_UNITS.get(key, "")
        if m.get("n", 0) == 0:
            rows.append([TRAIT_LABELS.get(key, key), "-", "-", "-", "-", "-", "0"])
            continue
        rows.append([
            TRAIT_LABELS.get(key, key) + (f" ({unit})" if unit else ""),
            f"{m['r2']:.3f}",
            f"{m['rmse']:.3f}",
            f"{m['mape']:.2f}%",
            f"{m['mae']:.3f}",
            f"{m['acc']:.2f}%",
            str(m["n"]),
        ])
    if fmt == "latex":
        lines = [r"\begin{tabular}{c|cccccc}", r"\hline", " & ".join(["", "$R^2$", "RMSE", "MAPE", "MAE", "Acc", "$n$"])
                 + r" \\ \hline \hline"]
        lines += [" & ".join(r).replace("%", r"\%") + r" \\" for r in rows]
        lines += [r"\hline", r"\end{tabular}"]
        return "\n".join(lines) + "\n"
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def scatter_plots(
    estimates: Sequence[Mapping] | Mapping,
    truths: Sequence[Mapping] | Mapping,
    traits: Sequence[str] = ("height_cm", "width1_cm", "width2_cm"),
    path: str | Path = "scatter.png",
    title: str = "",
) -> None:
    """The paper's figure: one panel per trait, estimate vs truth, the fitted line (red, solid), the
    ideal y = x (black, dashed) and R2 / RMSE / MAPE in the corner. Written atomically as PNG.

    Usage:
        scatter_plots(estimates, truths, ["height_cm"], "bench/scatter.png")
    """
    matplotlib.use("Agg")
    table = accuracy_table(estimates, truths, traits)
    fig, axs = plt.subplots(1, len(traits), figsize=(PANEL_SIZE_IN * len(traits), PANEL_SIZE_IN), squeeze=False)
    for ax, key in zip(axs[0], traits):
        y, yh = _align(estimates, truths, key)
        ok = np.isfinite(y) & np.isfinite(yh)
        y, yh = y[ok], yh[ok]
        unit = TRAIT_UNITS.get(key, "")
        label = TRAIT_LABELS.get(key, key)
        if len(y) == 0:
            ax.set_title(f"{label}: no data")
            continue
        lo = min(y.min(), yh.min())
        hi = max(y.max(), yh.max())
        pad = PLOT_PAD * (hi - lo if hi > lo else max(abs(hi), 1.0))
        lim = (lo - pad, hi + pad)
        ax.scatter(y, yh, s=MARKER_AREA, c="tab:blue", edgecolors="k", linewidths=0.5, zorder=3)
        ax.plot(lim, lim, "k--", lw=IDEAL_LINE_WIDTH, label="y = x")
        m = table[key]
        if np.isfinite(m.get("slope", np.nan)):
            xs = np.array(lim)
            ax.plot(xs, m["slope"] * xs + m["intercept"], "r-", lw=FIT_LINE_WIDTH,
                    label=f"fit y = {m['slope']:.2f}x {m['intercept']:+.2f}")
        ax.set_xlim(lim)
        ax.set_ylim(lim)
        ax.set_aspect("equal")
        u = f" ({unit})" if unit else ""
        ax.set_xlabel(f"ground truth{u}")
        ax.set_ylabel(f"estimate{u}")
        ax.set_title(label)
        ax.text(*STATS_CORNER, f"$R^2$ = {m['r2']:.3f}\nRMSE = {m['rmse']:.2f}{u and ' ' + unit}\n"
                f"MAPE = {m['mape']:.2f} %\nn = {m['n']}", transform=ax.transAxes, va="top", fontsize=STATS_FONT_SIZE)
        ax.legend(loc="lower right", fontsize=LEGEND_FONT_SIZE)
        ax.grid(alpha=GRID_ALPHA)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=PLOT_DPI)
    plt.close(fig)

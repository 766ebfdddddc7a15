"""Human-readable summaries printed at the end of `run`, `demo`, `evaluate` and `batch`."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from rich.table import Table

from plantsplat.log import console
from plantsplat.traitdefs import TRAIT_KEYS, TRAIT_LABELS, TRAIT_UNITS


def _num(v, key: str = "") -> str:
    if v is None:
        return "—"
    if key == "fruit_count":
        return str(int(round(float(v))))
    return f"{float(v):.2f}"


def print_summary(summary: dict, comparison: dict | None = None) -> None:
    """Print traits (with ground truth and errors when given), image metrics, stage times and outputs."""
    traits = summary.get("traits") or {}
    if traits.get("quality") == "failed":  # first, before any number: these must not be used
        console.print("[bold red]RESULT FAILED its checks: do not use these traits.[/] "
                      + "; ".join(traits.get("quality_reasons", [])[:3]))
    if traits:
        t = Table(title="Plant traits" + (" (FAILED)" if traits.get("quality") == "failed" else ""))
        t.add_column("trait")
        t.add_column("estimate", justify="right")
        if comparison:
            t.add_column("truth", justify="right")
            t.add_column("error", justify="right")
            t.add_column("error %", justify="right")
        t.add_column("unit")
        for key in TRAIT_KEYS:
            row = [TRAIT_LABELS[key], _num(traits.get(key), key)]
            if comparison:
                c = comparison.get(key) or {}
                row += [_num(c.get("truth"), key), _num(c.get("error")),
                        "—" if c.get("pct_error") is None else f"{c['pct_error']:.2f}"]
            row.append(TRAIT_UNITS[key])
            t.add_row(*row)
        console.print(t)
        flag = traits.get("quality")
        if flag and flag != "ok":
            console.print(f"[yellow]quality: {flag}[/] {'; '.join(traits.get('quality_reasons', []) or [])}")
        if traits.get("scale_source"):
            console.print(f"scale source: {traits['scale_source']}")
    metrics = summary.get("metrics") or {}
    flat = {k: v for k, v in flatten(metrics).items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
    if flat:
        m = Table(title="Image metrics (test views)")
        m.add_column("metric")
        m.add_column("value", justify="right")
        for k, v in list(flat.items())[:24]:
            m.add_row(k, f"{v:.4g}")
        console.print(m)
    run = summary.get("run") or {}
    if run.get("stages"):
        s = Table(title="Stages")
        s.add_column("stage")
        s.add_column("seconds", justify="right")
        s.add_column("peak MB", justify="right")
        for name, e in run["stages"].items():
            s.add_row(name, f"{e.get('seconds', 0):.1f}", f"{e.get('peak_rss_mb', 0):.0f}")
        console.print(s)
    for name, path in (summary.get("outputs") or {}).items():
        console.print(f"  {name:14s} {path}")


def flatten(d: Mapping[str, Any], sep: str = ".", prefix: str = "") -> dict[str, Any]:
    """Nested mappings flattened to one level, keys joined with ``sep``.

    Example:
        >>> flatten({"name": "a", "composite": {"psnr": 30.0}})
        {'name': 'a', 'composite.psnr': 30.0}
    """
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(flatten(v, sep, key + sep))
        else:
            out[key] = v
    return out

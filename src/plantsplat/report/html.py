"""Small HTML building blocks for the reports: escaping, tables, embedded images, sections.

Every image is embedded as a ``data:`` URI and every script is inlined, so a report is one file that
opens from ``file://`` with no network.

Example:
    >>> kv_table({"height_cm": 21.5, "fruit_count": 3})
    '<table class="kv"><tr><th>height_cm</th><td>21.50</td></tr><tr><th>fruit_count</th><td>3</td></tr></table>'
"""

from __future__ import annotations

import base64
import html
import math
from collections.abc import Mapping, Sequence
from importlib import resources
from typing import Any

import cv2
import numpy as np

from plantsplat.summary import flatten as flatten_keys


def esc(text: Any) -> str:
    """HTML-escape ``str(text)``."""
    return html.escape(str(text), quote=True)


def fmt_value(v: Any, digits: int = 2) -> str:
    """Format a number for a table: ints as is, floats with ``digits`` decimals (3 significant when small)."""
    if v is None:
        return "&ndash;"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        f = float(v)
        if math.isnan(f):
            return "n/a"
        if math.isinf(f):
            return "&infin;" if f > 0 else "&minus;&infin;"
        if f != 0 and abs(f) < 1:
            return f"{f:.4g}"  # metrics such as SSIM 0.9875 keep their digits
        return f"{f:.{digits}f}"
    if isinstance(v, (list, tuple)):
        if len(v) > 8:
            return esc(f"[{len(v)} values]")
        return ", ".join(fmt_value(x, digits) for x in v)
    return esc(v)


def is_number(v: Any) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)


def kv_table(d: Mapping[str, Any], cls: str = "kv", labels: Mapping[str, str] | None = None) -> str:
    """A two-column key/value table."""
    labels = labels or {}
    rows = "".join(f"<tr><th>{esc(labels.get(k, k))}</th><td>{fmt_value(v)}</td></tr>" for k, v in d.items())
    return f'<table class="{cls}">{rows}</table>'


def rows_table(rows: Sequence[Mapping[str, Any]], columns: Sequence[str], labels: Mapping[str, str] | None = None,
               cls: str = "grid", raw_html_columns: Sequence[str] = ()) -> str:
    """A table with one row per mapping; ``raw_html_columns`` are inserted without escaping."""
    labels = labels or {}
    head = "".join(f"<th>{esc(labels.get(c, c))}</th>" for c in columns)
    body = []
    for r in rows:
        cells = []
        for c in columns:
            v = r.get(c)
            cells.append(f"<td>{v if (c in raw_html_columns and v is not None) else fmt_value(v)}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    return f'<table class="{cls}"><thead><tr>{head}</tr></thead><tbody>{"".join(body)}</tbody></table>'


def generic_tables(d: Mapping[str, Any], title: str | None = None, depth: int = 0) -> str:
    """Render any JSON-like mapping: scalars as a key/value table, nested mappings as sub-tables.

    A mapping whose values are all mappings (e.g. per-view metrics) becomes one table with a row per key.
    """
    def is_records(v: Any) -> bool:
        return isinstance(v, list) and len(v) > 0 and all(isinstance(x, Mapping) for x in v)

    scalars = {k: v for k, v in d.items() if not isinstance(v, Mapping) and not is_records(v)}
    nested = {k: v for k, v in d.items() if isinstance(v, Mapping)}
    records = {k: v for k, v in d.items() if is_records(v)}
    out = []
    if title:
        out.append(f"<h4>{esc(title)}</h4>")
    if scalars:
        out.append(kv_table(scalars))
    for k, v in nested.items():
        if v and all(isinstance(x, Mapping) for x in v.values()):
            cols: list[str] = []
            for x in v.values():
                cols += [c for c in x if c not in cols and not isinstance(x[c], Mapping)]
            rows = [{"": name, **x} for name, x in v.items()]
            out.append(f"<h4>{esc(k)}</h4>" + rows_table(rows, ["", *cols]))
        elif depth < 3:
            out.append(generic_tables(v, title=str(k), depth=depth + 1))
    for k, v in records.items():  # e.g. per-view metrics as a list of dicts: one row each
        flat = [flatten_for_table(x) for x in v]
        cols: list[str] = []
        for x in flat:
            cols += [c for c in x if c not in cols]
        out.append(f"<h4>{esc(k)}</h4>" + rows_table(flat, cols))
    return "".join(out)


def flatten_for_table(d: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested mappings flattened to one level with ``"outer inner"`` keys.

    Example:
        >>> flatten_for_table({"name": "a", "composite": {"psnr": 30.0}})
        {'name': 'a', 'composite psnr': 30.0}
    """
    return flatten_keys(d, " ", prefix)


def img_tag(data: bytes, mime: str = "image/png", alt: str = "", cls: str = "", width: int | None = None) -> str:
    """An ``<img>`` with the image embedded as a base64 ``data:`` URI."""
    b64 = base64.b64encode(data).decode("ascii")
    w = f' width="{width}"' if width else ""
    c = f' class="{cls}"' if cls else ""
    return f'<img{c}{w} alt="{esc(alt)}" src="data:{mime};base64,{b64}">'


def encode_image(rgb: np.ndarray, fmt: str = ".jpg", quality: int = 85) -> bytes:
    """Encode an RGB(A) uint8 image [H, W, C] as JPEG or PNG bytes."""
    img = np.asarray(rgb)
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_RGBA2BGRA)
    params = [cv2.IMWRITE_JPEG_QUALITY, quality] if fmt == ".jpg" else [cv2.IMWRITE_PNG_COMPRESSION, 6]
    ok, buf = cv2.imencode(fmt, img, params)
    if not ok:
        raise ValueError("image encoding failed")
    return buf.tobytes()


def missing_note(what: str, hint: str) -> str:
    """A visible 'missing' box: what is absent and the command that produces it."""
    return f'<div class="missing"><b>Missing:</b> {esc(what)}. <span class="hint">{esc(hint)}</span></div>'


def error_note(message: str) -> str:
    return f'<div class="missing"><b>Could not show this part:</b> {esc(message)}</div>'


def section(sec_id: str, title: str, body: str) -> str:
    return f'<section id="{esc(sec_id)}"><h2>{esc(title)}</h2>{body}</section>'


def asset_text(name: str) -> str:
    """Text of a file in ``plantsplat/report/assets`` (vendored viewer, CSS, viewer app)."""
    return resources.files("plantsplat.report").joinpath("assets", name).read_text(encoding="utf-8")


def inline_script(code: str) -> str:
    """A classic inline ``<script>``; ``</script`` inside the code is escaped so it cannot end the tag."""
    return "<script>" + code.replace("</script", "<\\/script") + "</script>"


def data_block(block_id: str, data: bytes) -> str:
    """Binary data as base64 text in a non-executed ``<script type="application/octet-stream">`` block."""
    return (f'<script type="application/octet-stream" id="{esc(block_id)}">'
            + base64.b64encode(data).decode("ascii") + "</script>")


def page(title: str, body: str, head_extra: str = "") -> str:
    """A complete HTML document with the report stylesheet inlined."""
    return (
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
        "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
        f"<title>{esc(title)}</title><style>{asset_text('report.css')}</style>{head_extra}</head>"
        f"<body>{body}</body></html>\n"
    )

"""Named checks of a stage's result against what the capture itself says.

A :class:`Check` holds a measured value, the threshold it is held to and what failing it means
(``severity``: ``fail`` makes the result failed, ``warn`` a warning). The poses stage, the segment
stage and the traits stage record theirs in their JSON outputs; ``traits.json``'s ``quality``
is decided by all of them (:func:`quality`).

Example:
    >>> c = Check("registered_share", 118 / 120, 0.8, ">=")
    >>> c.passed, quality([c, Check("cube_edge_pct", 4.0, 3.0, "<=", severity="warn")])
    (True, 'warning')
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Check:
    """One named check: ``value`` compared with ``threshold`` by ``op`` (``>=`` or ``<=``)."""

    name: str
    value: float | None
    threshold: float
    op: str = "<="
    detail: str = ""
    severity: str = "fail"
    """What failing it means: ``fail`` (the result cannot be trusted) or ``warn`` (look at it)."""

    @property
    def passed(self) -> bool:
        if self.value is None or not np.isfinite(self.value):
            return False
        return self.value >= self.threshold if self.op == ">=" else self.value <= self.threshold

    def as_dict(self) -> dict:
        v = None if self.value is None else round(float(self.value), 4)
        return {"name": self.name, "value": v, "threshold": self.threshold, "op": self.op, "passed": self.passed,
                "severity": self.severity, "detail": self.detail}

    @classmethod
    def from_dict(cls, d: dict) -> Check:
        return cls(d["name"], d.get("value"), d["threshold"], d.get("op", "<="), d.get("detail", ""),
                   d.get("severity", "fail"))

    def line(self) -> str:
        v = "n/a" if self.value is None else f"{self.value:.3g}"
        return f"{self.name} {v} (needs {self.op} {self.threshold:g}){': ' + self.detail if self.detail else ''}"




def quality(checks: list[Check]) -> str:
    """``failed`` when a check of severity ``fail`` fails, ``warning`` when a ``warn`` one does, else ``ok``."""
    if any(not c.passed and c.severity == "fail" for c in checks):
        return "failed"
    return "warning" if any(not c.passed for c in checks) else "ok"

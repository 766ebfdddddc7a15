"""One record of each stage's state: what it read, what it wrote, with which options, and whether it succeeded.

Every stage runs through :func:`run_stage`, alike for ``plantsplat run``, ``batch`` and the stage's own
command. The record, ``WS/.plantsplat/stages/<stage>.json``, holds the stage's status (``ok``,
``failed`` with the reason, or ``running`` while it works), its options and the fingerprints of the
files it read and wrote. A stage is up to date only when its record says ``ok`` and matches today's
options, inputs and outputs (:func:`up_to_date`):

- a failed or interrupted stage (``failed``, ``running``) is run again, never built on: a stage whose
  upstream stage is not ``ok``, or is out of date (a stage before it wrote one of its inputs again after it
  ran), refuses to start (:func:`require_ok`);
- a changed upstream output changes a downstream stage's inputs, so the downstream stage runs again;
- a damaged output (truncated, edited, deleted) no longer matches its fingerprint: the stage runs again.

A file's fingerprint is its size and modification time (as ``make`` and ``rsync`` compare files); a
folder's is that of every file in it.

Usage:
    rec = read_record(Workspace("ws/plant01"), "poses")
    rec["status"], rec["config"]["matcher"]
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from plantsplat.errors import PlantsplatError
from plantsplat.io import write_json_atomic
from plantsplat.lock import workspace_lock
from plantsplat.log import get_logger
from plantsplat.workspace import Workspace

log = get_logger(__name__)

RECORD_DIR = ".plantsplat/stages"
RECORD_VERSION = 1


def record_path(ws: Workspace, stage: str) -> Path:
    return ws.root / RECORD_DIR / f"{stage}.json"


def fingerprint(path: Path) -> str | None:
    """Size and modification time of a file, or of every file in a folder (recursively); None when missing."""
    if path.is_file():
        st = path.stat()
        return f"{st.st_size}:{st.st_mtime_ns}"
    if not path.is_dir():
        return None
    h = hashlib.sha1()
    for root, dirs, files in os.walk(path):
        dirs.sort()
        for f in sorted(files):
            p = Path(root) / f
            st = p.stat()
            h.update(f"{p.relative_to(path)}:{st.st_size}:{st.st_mtime_ns}\n".encode())
    return "dir:" + h.hexdigest()[:20]


def fingerprints(ws: Workspace, paths: Iterable[Path]) -> dict[str, str | None]:
    """``{path (relative to the workspace when inside it): fingerprint}``."""
    out = {}
    for p in paths:
        p = Path(p)
        try:
            key = str(p.resolve().relative_to(ws.root.resolve()))
        except ValueError:
            key = str(p.resolve())
        out[key] = fingerprint(p)
    return out


def config_dict(cfg: Any) -> dict:
    """A stage's options as JSON (dataclasses, paths as strings)."""
    if cfg is None:
        return {}
    d = dataclasses.asdict(cfg) if dataclasses.is_dataclass(cfg) else dict(cfg)
    return json.loads(json.dumps(d, default=str, sort_keys=True))


def read_record(ws: Workspace, stage: str) -> dict | None:
    """The stage's record, or None when there is none (or it is unreadable: then the stage simply runs again)."""
    p = record_path(ws, stage)
    try:
        rec = json.loads(p.read_text())
    except (OSError, ValueError):
        return None
    return rec if isinstance(rec, dict) and rec.get("version") == RECORD_VERSION else None


def _write(ws: Workspace, stage: str, **fields) -> dict:
    rec = {"version": RECORD_VERSION, "stage": stage, "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"), **fields}
    write_json_atomic(record_path(ws, stage), rec)
    return rec


def up_to_date(ws: Workspace, stage: str, config: dict, inputs: list[Path], outputs: list[Path]) -> tuple[bool, str]:
    """Whether the stage's record says ``ok`` for these options, today's inputs and its outputs as it wrote them;
    with the reason when not."""
    rec = read_record(ws, stage)
    if rec is None:
        return False, "not run yet"
    if rec.get("status") != "ok":
        return False, f"its last run {rec.get('status')}" + (f" ({rec['reason']})" if rec.get("reason") else "")
    if rec.get("config") != config:
        changed = sorted(k for k in set(config) | set(rec.get("config", {}))
                         if config.get(k) != rec.get("config", {}).get(k))
        return False, f"options changed ({', '.join(changed[:4])})"
    now_in = fingerprints(ws, inputs)
    if rec.get("inputs") != now_in:
        changed = sorted(k for k in now_in if now_in[k] != rec.get("inputs", {}).get(k))
        return False, f"inputs changed ({', '.join(changed[:3]) or 'their list'})"
    now_out = fingerprints(ws, outputs)
    if rec.get("outputs") != now_out:
        changed = sorted(k for k in now_out if now_out[k] != rec.get("outputs", {}).get(k))
        return False, f"outputs missing or changed since it wrote them ({', '.join(changed[:3])})"
    return True, "up to date"


def require_ok(ws: Workspace, stage: str, command: str | None = None) -> None:
    """Refuse to build on a stage that failed, was interrupted or is out of date: a one-line error naming what to
    run.

    Out of date: a stage before it has written one of its inputs again since it ran (``plantsplat train --force``,
    then the traits of the previous model's export). The records are compared with each other, not with the files,
    so a copied workspace, whose files all have new times, is not out of date. A workspace whose files were made
    without the stage (no record: images, poses or masks put there by hand or by an importer) is left to the next
    stage's own checks of its inputs.
    """
    rec = read_record(ws, stage)
    if rec is None:
        return
    cmd = command or f"plantsplat {stage} {ws.root}"
    if rec.get("status") != "ok":
        reason = f": {rec['reason']}" if rec.get("reason") else ""
        raise PlantsplatError(f"{ws.root}: the {stage} stage {rec.get('status')}{reason}; fix that and run `{cmd}` "
                              "again (nothing is built on it)")
    rewritten = rewritten_inputs(ws, rec)
    if rewritten:
        before, path = rewritten[0]
        raise PlantsplatError(f"{ws.root}: the {stage} stage is out of date: the {before} stage wrote {path} again "
                              f"after it ran; run `{cmd}` again (nothing is built on an out-of-date stage)")


def rewritten_inputs(ws: Workspace, rec: dict) -> list[tuple[str, str]]:
    """``(stage, path)`` for each input of the stage record ``rec`` that another stage's ``ok`` record says it wrote
    after ``rec``'s stage finished, with another fingerprint than that stage read. (A file changed by hand is not
    a stage's writing: the stage that reads it next runs again, as its inputs changed.)"""
    out = []
    for other in sorted((ws.root / RECORD_DIR).glob("*.json")):
        o = read_record(ws, other.stem)
        if (o is None or o.get("status") != "ok" or other.stem == rec.get("stage")
                or not o.get("finished", 0) > rec.get("finished", float("inf"))):
            continue
        written, read = o.get("outputs") or {}, rec.get("inputs") or {}
        out += [(other.stem, p) for p in sorted(set(written) & set(read)) if written[p] != read[p]]
    return out


def run_stage(ws: Workspace, stage: str, config: Any, inputs: list[Path], outputs: list[Path],
              work: Callable[[bool], dict], force: bool = False) -> dict:
    """Run ``work`` unless the stage is up to date, recording the outcome (see the module docstring).

    ``work(resume)`` does the stage; ``resume`` is True when the last run of the stage was interrupted with the
    same options and inputs (a stage that keeps checkpoints may go on from them; otherwise it starts afresh).
    Returns the stage's result (the one recorded when it was up to date). A :class:`PlantsplatError`
    (or an interruption) leaves the record ``failed`` (``running``), and is raised on. The workspace's lock
    (:mod:`plantsplat.lock`) is held throughout: another process working on it is refused.
    """
    with workspace_lock(ws.root):
        return _run_locked(ws, stage, config, inputs, outputs, work, force)


def _run_locked(ws: Workspace, stage: str, config: Any, inputs: list[Path], outputs: list[Path],
                work: Callable[[bool], dict], force: bool) -> dict:
    cfg = config_dict(config)
    rec = read_record(ws, stage)
    now_in = fingerprints(ws, inputs)
    if not force:
        ok, why = up_to_date(ws, stage, cfg, inputs, outputs)
        if ok:
            log.info("[%s] up to date, skipped (pass --force to redo)", stage)
            return dict(rec.get("result") or {}, up_to_date=True)
        if rec is not None:
            log.info("[%s] runs again: %s", stage, why)
    resume = (not force and rec is not None and rec.get("status") == "running" and rec.get("config") == cfg
              and rec.get("inputs") == now_in)
    _write(ws, stage, status="running", config=cfg, inputs=now_in)
    try:
        result = work(resume)
    except PlantsplatError as exc:
        try:
            _write(ws, stage, status="failed", reason=str(exc), config=cfg, inputs=now_in)
        except PlantsplatError as also:  # a full disk fails this write too: the stage's own error is the one to say
            log.warning("[%s] could not record the failure (%s); the record says running, so the next run redoes "
                        "the stage", stage, also)
        raise
    _write(ws, stage, status="ok", config=cfg, inputs=fingerprints(ws, inputs), outputs=fingerprints(ws, outputs),
           result=_jsonable(result), finished=time.time())
    return result


def _jsonable(result: Any) -> Any:
    """The scalars of a stage's result (what later runs return when it is up to date)."""
    if not isinstance(result, dict):
        return {}
    return {k: v for k, v in result.items() if isinstance(v, (int, float, str, bool)) or v is None}

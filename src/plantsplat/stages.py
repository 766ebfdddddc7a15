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
import datetime
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
    then the traits of the previous model's export), or one of the stages it was built on is out of date
    (``plantsplat segment --force``, then the traits of an export of the model trained on the old masks). The
    records are compared with each other, not with the files, so a copied workspace, whose files all have new
    times, is not out of date; their times are the clock's, so a workspace moved to a machine whose clock is far
    behind can miss a stage run there. A workspace whose files were made without the stage (no record: images,
    poses or masks put there by hand or by an importer) is left to the next stage's own checks of its inputs.
    """
    rec = read_record(ws, stage)
    if rec is None:
        return
    cmd = command or f"plantsplat {stage} {ws.root}"
    if rec.get("status") != "ok":
        reason = f": {rec['reason']}" if rec.get("reason") else ""
        raise PlantsplatError(f"{ws.root}: the {stage} stage {rec.get('status')}{reason}; fix that and run `{cmd}` "
                              "again (nothing is built on it)")
    stale = out_of_date(ws, stage)
    if stale is None:
        return
    first, writer, path = stale
    if first == stage:
        raise PlantsplatError(f"{ws.root}: the {stage} stage is out of date: the {writer} stage wrote {path} again "
                              f"after it ran; run `{cmd}` again (nothing is built on an out-of-date stage)")
    raise PlantsplatError(f"{ws.root}: the {stage} stage is out of date: it was built on the {first} stage, and the "
                          f"{writer} stage wrote {path} again after that ran; run `plantsplat {first} {ws.root}` and "
                          "the stages after it again (nothing is built on an out-of-date stage)")


def out_of_date(ws: Workspace, stage: str) -> tuple[str, str, str] | None:
    """Why the ``ok`` stage ``stage`` is out of date: ``(stale stage, writer, path)``, where ``stale stage`` is the
    stage itself or one it was built on (see :func:`built_on`), the first of them where several are (one built on
    no other stale stage), and ``writer`` the stage that wrote ``path``, one of the stale stage's inputs, after it
    finished. None when it is up to date with every stage it was built on."""
    records = {}
    for path in sorted((ws.root / RECORD_DIR).glob("*.json")):
        rec = read_record(ws, path.stem)
        if rec is not None and rec.get("status") == "ok":
            records[path.stem] = rec
    if stage not in records:
        return None
    stale = {}
    for name in sorted(built_on(records, stage) | {stage}):
        rewritten = rewritten_inputs(records, name)
        if rewritten:
            stale[name] = rewritten[0]
    first = [name for name in stale if not built_on(records, name) & set(stale)] or list(stale)
    return (first[0], *stale[first[0]]) if stale else None


def built_on(records: dict[str, dict], stage: str) -> set[str]:
    """The stages ``stage`` was built on (``records``: stage name -> ``ok`` record): those whose outputs it read,
    and those whose outputs they read, and so on back."""
    found, todo = set(), [stage]
    while todo:
        read = set(records[todo.pop()].get("inputs") or {})
        for other, rec in records.items():
            if other != stage and other not in found and read & set(rec.get("outputs") or {}):
                found.add(other)
                todo.append(other)
    return found


def rewritten_inputs(records: dict[str, dict], stage: str) -> list[tuple[str, str]]:
    """``(writer, path)`` for each input of ``stage`` that another stage's ``ok`` record (``records``: stage name ->
    ``ok`` record) says it wrote after ``stage`` finished, with another fingerprint than ``stage`` read. (A file
    changed by hand is not a stage's writing: the stage that reads it next runs again, as its inputs changed.)"""
    rec, out = records[stage], []
    since = finished_at(rec)
    if since is None:
        return out
    for other, o in records.items():
        done = finished_at(o)
        if other == stage or done is None or not done > since:
            continue
        written, read = o.get("outputs") or {}, rec.get("inputs") or {}
        out += [(other, p) for p in sorted(set(written) & set(read)) if written[p] != read[p]]
    return out


def finished_at(rec: dict) -> float | None:
    """When an ``ok`` record's stage finished (seconds since the epoch): its ``finished`` field, or for a record
    written before that field existed its ``time`` (to the second); None when neither can be read."""
    if isinstance(rec.get("finished"), (int, float)):
        return float(rec["finished"])
    try:
        return datetime.datetime.strptime(str(rec.get("time")), "%Y-%m-%dT%H:%M:%S%z").timestamp()
    except ValueError:
        return None


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

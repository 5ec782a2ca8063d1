"""Refinement jobs as small JSON files beside the scenes, so every process sharing the store answers them.

``<store root>/jobs/<id>.json`` holds a job's record (:meth:`service.jobs.Job.as_json`) plus
``owner`` (``host``, ``pid``, ``replica``) and ``heartbeat`` (unix time of the last write),
written atomically (temporary file + ``os.replace``). The owner rewrites its queued/running
records every :data:`HEARTBEAT_S`; any reader sees such a record as *lost* when its heartbeat is
older than :data:`STALE_S`, or at once when the owner ran on this host and its process is gone.
At start-up (:meth:`JobFiles.sweep`) such records are rewritten as failed, and finished ones older than
:data:`RETENTION_S` (or beyond :data:`MAX_RECORDS`) are removed. Nothing here knows about HTTP or the model.
"""

from __future__ import annotations

import json
import os
import socket
import time
import uuid
from pathlib import Path

from .store import check_scene_id

#: seconds between an owner's rewrites of its unfinished job records
HEARTBEAT_S = 2.0
#: an unfinished record whose heartbeat is older than this is reported failed
STALE_S = 30.0
#: finished records (done / failed) older than this are removed at start-up
RETENTION_S = 7 * 24 * 3600.0
#: at most this many records are kept (the oldest finished ones go first)
MAX_RECORDS = 10_000
ACTIVE = ("queued", "running")
#: every status a record may hold
STATUSES = (*ACTIVE, "done", "failed")
#: a record's fields that hold a unix time or a fraction (a number, or null)
_NUMBERS = ("progress", "created_at", "started_at", "finished_at", "heartbeat")
#: a record's fields that hold an object (or null)
_OBJECTS = ("params", "error", "owner")


def identity(replica: str | None = None) -> dict:
    """This process as a job owner: host, pid and a replica name (default ``host:pid``)."""
    host, pid = socket.gethostname(), os.getpid()
    return {"host": host, "pid": pid, "replica": replica or f"{host}:{pid}"}


def _mtime(path: Path) -> float:
    try:
        return path.stat().st_mtime
    except OSError:
        return float("inf")


def well_formed(record, job_id: str) -> bool:
    """Whether ``record`` is a job record of ``job_id`` that readers can rely on: its id, a known status, a
    parent id, numbers where times and progress go and objects where params, error and owner go. Records are
    written atomically, so anything else is a damaged file (disk damage, an outside edit), which is reported
    as no record rather than failing every reader, start-up included."""
    if not isinstance(record, dict) or record.get("id") != job_id or record.get("status") not in STATUSES:
        return False
    if not isinstance(record.get("parent_id"), str):
        return False
    numbers = all(v is None or (isinstance(v, (int, float)) and not isinstance(v, bool))
                  for v in map(record.get, _NUMBERS))
    return numbers and all(v is None or isinstance(v, dict) for v in map(record.get, _OBJECTS))


def _same_owner(record: dict, owner: dict) -> bool:
    """Whether ``record`` names ``owner`` (host, pid and replica) as its owner."""
    named = record.get("owner") or {}
    return all(named.get(k) == owner.get(k) for k in ("host", "pid", "replica"))


def _process_gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except (PermissionError, OverflowError):
        return False
    return False


class JobFiles:
    """Job records in one folder shared by every replica (a ReadWriteMany volume on a cluster)."""

    def __init__(self, root: str | Path, owner: dict | None = None, stale_s: float = STALE_S,
                 retention_s: float = RETENTION_S, max_records: int = MAX_RECORDS) -> None:
        self.dir = Path(root)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.owner = owner or identity()
        self.stale_s = stale_s
        self.retention_s = retention_s
        self.max_records = max_records
        self.sweep(start_up=True)

    def sweep(self, now: float | None = None, *, start_up: bool = False) -> dict[str, int]:
        """Start-up housekeeping: a record whose owner is gone (killed while queued or running) is rewritten
        as ``failed`` (``replica_lost``); finished records older than ``retention_s``, records beyond
        ``max_records`` (oldest finished first) and interrupted writes are removed. Returns the counts.

        ``start_up``: this owner has no job yet, so an unfinished record that names this very owner (host, pid
        and replica) is a previous process's that had the same identity: a restarted container's server,
        whose pid and host name come back the same."""
        now = time.time() if now is None else now
        out = {"failed": 0, "removed": 0}
        for leftover in self.dir.glob(".*.tmp"):
            if now - _mtime(leftover) > self.stale_s:  # another replica's write may be in flight
                leftover.unlink(missing_ok=True)
        finished: list[tuple[float, Path]] = []
        for path in self.dir.glob("*.json"):
            record = self.read(path.stem) if len(path.stem) == 32 else None
            if record is None:
                continue
            reason = self.lost(record, now)
            if reason is None and start_up and record.get("status") in ACTIVE and _same_owner(record, self.owner):
                reason = (f"the process before this one with the same identity (replica {self.owner['replica']}) "
                          f"exited while the job was {record['status']}; submit it again")
            if reason is not None:
                owner = record.get("owner") or {}
                record.update(status="failed", finished_at=now, error={"code": "replica_lost", "message": reason})
                self._write_as(record, owner)
                out["failed"] += 1
            if record.get("status") not in ACTIVE:
                when = float(record.get("finished_at") or record.get("heartbeat") or 0.0)
                finished.append((when, path))
        finished.sort()
        total = len(list(self.dir.glob("*.json")))
        for when, path in finished:
            if now - when > self.retention_s or total > self.max_records:
                path.unlink(missing_ok=True)
                total -= 1
                out["removed"] += 1
        return out

    def _write_as(self, record: dict, owner: dict) -> None:
        """Rewrite a record keeping its owner and heartbeat (start-up marks another process's lost job)."""
        target = self.path(record["id"])
        tmp = self.dir / f".{target.name}.{uuid.uuid4().hex}.tmp"
        try:
            tmp.write_bytes(json.dumps({**record, "owner": owner}).encode())
            os.replace(tmp, target)
        finally:
            tmp.unlink(missing_ok=True)

    def path(self, job_id: str) -> Path:
        return self.dir / f"{check_scene_id(job_id)}.json"

    def write(self, record: dict) -> None:
        """Write ``record`` (stamped with this owner and a fresh heartbeat) atomically."""
        target = self.path(record["id"])
        data = json.dumps({**record, "owner": self.owner, "heartbeat": time.time()}).encode()
        tmp = self.dir / f".{target.name}.{uuid.uuid4().hex}.tmp"
        try:
            with open(tmp, "wb") as f:
                f.write(data)
            os.replace(tmp, target)
        finally:
            tmp.unlink(missing_ok=True)

    def read(self, job_id: str) -> dict | None:
        """The stored record, or None when there is none (or it cannot be parsed, or is not :func:`well_formed`)."""
        try:
            record = json.loads(self.path(job_id).read_text())
        except (FileNotFoundError, ValueError):
            return None
        return record if well_formed(record, job_id) else None

    def lost(self, record: dict, now: float | None = None) -> str | None:
        """Why an unfinished record's owner is gone (None while it is alive or the job finished)."""
        if record.get("status") not in ACTIVE:
            return None
        owner = record.get("owner") or {}
        age = (now or time.time()) - float(record.get("heartbeat") or 0.0)
        who = f"replica {owner.get('replica')} (pid {owner.get('pid')} on {owner.get('host')})"
        if owner.get("host") == self.owner["host"] and isinstance(owner.get("pid"), int) \
                and owner["pid"] != self.owner["pid"] and _process_gone(owner["pid"]):
            return f"{who} exited while the job was {record['status']}; submit it again"
        if age > self.stale_s:
            return f"{who} stopped reporting {age:.0f} s ago (limit {self.stale_s:.0f} s); submit it again"
        return None

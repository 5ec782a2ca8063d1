"""Refinement jobs as small JSON files beside the scenes, so every process sharing the store answers them.

``<store root>/jobs/<id>.json`` holds a job's record (:meth:`service.jobs.Job.as_json`) plus
``owner`` (``host``, ``pid``, ``replica``) and ``heartbeat`` (unix time of the last write),
written atomically (temporary file + ``os.replace``). The owner rewrites its queued/running
records every :data:`HEARTBEAT_S`; any reader sees such a record as *lost* when its heartbeat is
older than :data:`STALE_S`, or at once when the owner ran on this host and its process is gone.
Nothing here knows about HTTP or the model.
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
ACTIVE = ("queued", "running")


def identity(replica: str | None = None) -> dict:
    """This process as a job owner: host, pid and a replica name (default ``host:pid``)."""
    host, pid = socket.gethostname(), os.getpid()
    return {"host": host, "pid": pid, "replica": replica or f"{host}:{pid}"}


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

    def __init__(self, root: str | Path, owner: dict | None = None, stale_s: float = STALE_S) -> None:
        self.dir = Path(root)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.owner = owner or identity()
        self.stale_s = stale_s

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
        """The stored record, or None when there is none (or it cannot be parsed)."""
        try:
            record = json.loads(self.path(job_id).read_text())
        except (FileNotFoundError, ValueError):
            return None
        return record if isinstance(record, dict) and record.get("id") == job_id else None

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

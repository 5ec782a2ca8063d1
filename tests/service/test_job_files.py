"""Job records at start-up: a job killed with its process is marked failed, old records are pruned."""

from __future__ import annotations

import json
import subprocess
import sys
import time

from service.job_state import JobFiles, identity


def _record(job_id: str, status: str, owner: dict, heartbeat: float, finished_at: float | None = None) -> dict:
    return {"id": job_id, "status": status, "progress": 0.5, "parent_id": "b" * 32, "params": {}, "error": None,
            "created_at": heartbeat, "started_at": heartbeat, "finished_at": finished_at, "owner": owner,
            "heartbeat": heartbeat}


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_start_up_marks_a_killed_job_failed_and_prunes_old_records(tmp_path):
    me = identity("me")
    now = time.time()
    dead = {**me, "pid": _dead_pid(), "replica": "killed"}
    records = {
        "1" * 32: _record("1" * 32, "running", dead, now),                       # killed -9 while running
        "2" * 32: _record("2" * 32, "done", dead, now - 30 * 86400, now - 30 * 86400),  # a month old
        "3" * 32: _record("3" * 32, "done", dead, now - 60, now - 60),            # recent: kept
        "4" * 32: _record("4" * 32, "running", {**me, "replica": "alive"}, now),  # this process: alive
    }
    for job_id, rec in records.items():
        (tmp_path / f"{job_id}.json").write_text(json.dumps(rec))
    (tmp_path / f".{'5' * 32}.json.abc.tmp").write_text("{")
    old = time.time() - 3600
    import os
    os.utime(tmp_path / f".{'5' * 32}.json.abc.tmp", (old, old))

    files = JobFiles(tmp_path, me)
    killed = files.read("1" * 32)
    assert killed["status"] == "failed" and killed["error"]["code"] == "replica_lost"
    assert killed["owner"]["replica"] == "killed"
    assert files.read("2" * 32) is None and not (tmp_path / f"{'2' * 32}.json").exists()
    assert files.read("3" * 32)["status"] == "done"
    assert files.read("4" * 32)["status"] == "running"
    assert not list(tmp_path.glob(".*.tmp"))


def test_record_count_is_capped_oldest_finished_first(tmp_path):
    me = identity("me")
    now = time.time()
    for k in range(6):
        job_id = f"{k:032x}"
        (tmp_path / f"{job_id}.json").write_text(json.dumps(_record(job_id, "failed", me, now - 100 + k, now - 100 + k)))
    files = JobFiles(tmp_path, me, max_records=4)
    assert sorted(p.stem for p in tmp_path.glob("*.json")) == [f"{k:032x}" for k in range(2, 6)]
    assert files.sweep() == {"failed": 0, "removed": 0}

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


def test_a_damaged_record_is_no_record_for_start_up_and_readers(tmp_path):
    """A record with a field of the wrong type (disk damage, an outside edit) neither stops start-up nor fails a
    reader: it reads as no record, and a new submission of that job writes a whole one over it."""
    from service.jobs import JobRegistry

    me = identity("me")
    now = time.time()
    good = _record("0" * 32, "running", me, now)
    damaged = {"1" * 32: {**good, "id": "1" * 32, "heartbeat": "abc"},
               "2" * 32: {**good, "id": "2" * 32, "status": "done", "finished_at": "yesterday"},
               "3" * 32: {**good, "id": "3" * 32, "owner": "me"},
               "4" * 32: {"id": "4" * 32, "status": "queued"},
               "5" * 32: {**good, "id": "5" * 32, "status": "paused"},
               "6" * 32: {**good, "id": "6" * 32, "error": "boom"}}
    for job_id, rec in damaged.items():
        (tmp_path / f"{job_id}.json").write_text(json.dumps(rec))
    files = JobFiles(tmp_path, me)  # start-up: the sweep reads every record
    registry = JobRegistry(files=files)
    for job_id in damaged:
        assert files.read(job_id) is None and registry.get(job_id) is None
    job, created = registry.submit("4" * 32, "b" * 32, {})
    assert created and files.read("4" * 32)["status"] == "queued"


def test_start_up_fails_the_jobs_of_a_previous_process_with_the_same_identity(tmp_path):
    """A restarted container's server comes back with the same host name and pid (and so the same default replica
    name): an unfinished record naming that identity is the previous process's, failed at start-up, not answered
    'running' until its heartbeat goes stale. Another replica of this process (another name) keeps its jobs."""
    me = identity()
    now = time.time()
    (tmp_path / f"{'1' * 32}.json").write_text(json.dumps(_record("1" * 32, "running", me, now)))
    (tmp_path / f"{'2' * 32}.json").write_text(json.dumps(_record("2" * 32, "queued", {**me, "replica": "other"}, now)))
    files = JobFiles(tmp_path, me)
    previous = files.read("1" * 32)
    assert previous["status"] == "failed" and previous["error"]["code"] == "replica_lost"
    assert "same identity" in previous["error"]["message"]
    assert files.read("2" * 32)["status"] == "queued"
    files.write(_record("3" * 32, "running", me, now))  # this process's own job: a later sweep keeps it
    assert files.sweep() == {"failed": 0, "removed": 0} and files.read("3" * 32)["status"] == "running"

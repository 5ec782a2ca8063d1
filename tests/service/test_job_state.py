"""Job records shared through the store: visible from another registry ("replica"), lost owners reported failed."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import pytest

from service.job_state import JobFiles, identity
from service.jobs import JobRegistry
from tests.service._support import LiveServer, make_settings, panorama, post_scene

JOB = "a" * 32
PARENT = "b" * 32


def two_replicas(tmp_path, stale_s: float = 30.0):
    one = JobRegistry(files=JobFiles(tmp_path, identity("one"), stale_s))
    two = JobRegistry(files=JobFiles(tmp_path, identity("two"), stale_s))
    return one, two


def test_a_job_is_answered_by_another_replica_with_progress(tmp_path, monkeypatch):
    monkeypatch.setattr("service.jobs.PROGRESS_WRITE_S", 0.0)  # every progress report written
    one, two = two_replicas(tmp_path)
    job, created = one.submit(JOB, PARENT, {"iterations": 3})
    assert created and two.get(JOB).status == "queued"
    one.mark_running(job)
    one.progress_callback(job)(0.4)
    seen = two.get(JOB)
    assert (seen.status, seen.progress, seen.owner["replica"]) == ("running", 0.4, "one")
    # the same request on the other replica joins the running job instead of starting a second one
    joined, created = two.submit(JOB, PARENT, {"iterations": 3})
    assert not created and joined.owner["replica"] == "one"
    one.mark_done(job)
    assert two.get(JOB).as_json()["scene_id"] == JOB
    one.cancel_all()


def test_failure_is_recorded_and_a_new_attempt_replaces_it(tmp_path):
    one, two = two_replicas(tmp_path)
    job, _ = one.submit(JOB, PARENT, {})
    one.mark_failed(job, RuntimeError("boom"))
    assert two.get(JOB).error == {"code": "RuntimeError", "message": "boom"}
    again, created = two.submit(JOB, PARENT, {})
    assert created and again.status == "queued" and one.get(JOB).owner["replica"] == "one"  # own memory first
    assert JobRegistry(files=JobFiles(tmp_path)).get(JOB).owner["replica"] == "two"
    one.cancel_all()
    two.cancel_all()


def test_stale_heartbeat_is_reported_failed_not_running(tmp_path):
    one, two = two_replicas(tmp_path, stale_s=5.0)
    job, _ = one.submit(JOB, PARENT, {})
    one.mark_running(job)
    one.cancel_all()  # stops the heartbeat
    path = tmp_path / f"{JOB}.json"
    record = json.loads(path.read_text())
    record["heartbeat"] -= 60
    record["owner"]["host"] = "elsewhere"  # not this host: only the heartbeat can tell
    path.write_text(json.dumps(record))
    seen = two.get(JOB)
    assert seen.status == "failed" and seen.error["code"] == "replica_lost"
    assert "stopped reporting" in seen.error["message"]
    # a new attempt is allowed and owned by the caller
    assert two.submit(JOB, PARENT, {})[1] is True


def test_an_owner_process_that_exited_is_reported_at_once(tmp_path):
    code = ("import sys; from service.jobs import JobRegistry; from service.job_state import JobFiles, identity; "
            f"r = JobRegistry(files=JobFiles(sys.argv[1], identity('doomed'))); j, _ = r.submit('{JOB}', '{PARENT}', {{}});"
            " r.mark_running(j)")
    subprocess.run([sys.executable, "-c", code, str(tmp_path)], check=True)
    files = JobFiles(tmp_path, identity("survivor"))  # start-up rewrites the lost record as failed
    on_disk = json.loads((tmp_path / f"{JOB}.json").read_text())
    assert on_disk["status"] == "failed" and on_disk["owner"]["replica"] == "doomed"
    seen = JobRegistry(files=files).get(JOB)
    assert seen.status == "failed" and "exited while the job was running" in seen.error["message"]
    assert files.lost({**on_disk, "status": "running"}) is not None


def test_the_heartbeat_keeps_a_slow_job_alive(tmp_path, monkeypatch):
    monkeypatch.setattr("service.jobs.HEARTBEAT_S", 0.05)
    one, two = two_replicas(tmp_path, stale_s=1.0)
    job, _ = one.submit(JOB, PARENT, {})
    one.mark_running(job)
    first = json.loads((tmp_path / f"{JOB}.json").read_text())["heartbeat"]
    deadline = time.monotonic() + 10
    while json.loads((tmp_path / f"{JOB}.json").read_text())["heartbeat"] == first:
        assert time.monotonic() < deadline, "no heartbeat written"
        time.sleep(0.02)
    assert two.get(JOB).status == "running"
    one.cancel_all()


def test_without_files_the_registry_stays_in_memory(tmp_path):
    reg = JobRegistry()
    job, created = reg.submit(JOB, PARENT, {})
    assert created and job.owner is None and "owner" not in job.as_json()
    assert JobRegistry().get(JOB) is None


@pytest.mark.parametrize("bad", ["../x", "A" * 32, ""])
def test_job_file_paths_stay_inside(tmp_path, bad):
    with pytest.raises(ValueError):
        JobFiles(tmp_path).path(bad)


def test_two_services_on_one_store_answer_each_others_jobs(model_path, tmp_path):
    """Two apps sharing a store (as Ray replicas do): a job POSTed to one is answered by the other."""
    settings = [make_settings(model_path, tmp_path, replica_id=name) for name in ("one", "two")]
    with LiveServer(settings[0]) as one, LiveServer(settings[1]) as two, one.client() as a, two.client() as b:
        r = post_scene(a, panorama(seed=5), panorama(seed=5, shift=4))
        assert r.status_code == 201, r.text
        sid = r.json()["id"]
        r = a.post(f"/v1/scenes/{sid}/refine", json={"iterations": 4, "height": 24, "patience": 0})
        assert r.status_code == 202, r.text
        location = r.headers["location"]
        first = b.get(location)
        assert first.status_code == 200 and first.json()["owner"]["replica"] == "one"
        # the same request to the other service joins the job instead of starting a second one
        joined = b.post(f"/v1/scenes/{sid}/refine", json={"iterations": 4, "height": 24, "patience": 0})
        assert joined.status_code == 202 and joined.headers["location"] == location
        deadline = time.monotonic() + 120
        while (body := b.get(location).json())["status"] not in ("done", "failed"):
            assert time.monotonic() < deadline
            time.sleep(0.05)
        assert body["status"] == "done" and b.get(f"/v1/scenes/{body['scene_id']}").status_code == 200
        counts = two.app.state.jobs.counts()  # the second service never ran it itself
        assert counts["queued"] == counts["running"] == counts["failed"] == 0

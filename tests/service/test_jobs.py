"""Refinement jobs over HTTP: 202 + Location, status flow, idempotent result id, 4xx on bad input."""

from __future__ import annotations

import dataclasses
import io
import time

import numpy as np
import pytest
from PIL import Image

from service.jobs import JobRegistry, result_id_for
from service.references import store_references
from tests.service._support import LiveServer, make_settings, panorama, post_scene

ZERO_ID = "0" * 32


@pytest.fixture(scope="module")
def live(model_path, tmp_path_factory):
    store = tmp_path_factory.mktemp("jobs-store")
    with LiveServer(make_settings(model_path, store)) as server:
        yield server


def _decode(data: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))


@pytest.fixture(scope="module")
def scene_id(client, live) -> str:
    a, b = panorama(seed=3), panorama(seed=3, shift=4)
    r = post_scene(client, a, b)
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    # scene creation keeps the references, at the model's input size, inside the scene folder
    path = live.app.state.store.artifact(sid, "references.npz")
    assert path is not None
    with np.load(path) as z:
        assert z["image_a"].dtype == np.uint8 and z["image_a"].shape == _decode(a).shape
        assert np.array_equal(z["image_b"], _decode(b))
    return sid


def test_scene_without_references_answers_409(client, live):
    r = post_scene(client, panorama(seed=9), panorama(seed=9, shift=6))
    sid = r.json()["id"]
    (live.app.state.store.artifact(sid, "references.npz")).unlink()
    r = client.post(f"/v1/scenes/{sid}/refine", json={})
    assert r.status_code == 409 and r.json()["error"]["code"] == "references_missing"
    store_references(live.app.state.store, sid, _decode(panorama(seed=9)), _decode(panorama(seed=9, shift=6)))
    assert client.post(f"/v1/scenes/{sid}/refine", json={"iterations": 1, "height": 24}).status_code == 202


def can_be_refined_again(client, scene_id) -> bool:
    """A refined scene carries its parent's references, so it can be refined again."""
    r = client.post(f"/v1/scenes/{scene_id}/refine", json={"iterations": 0, "height": 24})
    return r.status_code == 202


def _wait(client, location: str, timeout: float = 120.0) -> dict:
    seen = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        r = client.get(location)
        assert r.status_code == 200, r.text
        body = r.json()
        seen.append(body["progress"])
        assert body["status"] in ("queued", "running", "done", "failed")
        assert 0.0 <= body["progress"] <= 1.0
        if body["status"] in ("done", "failed"):
            assert seen == sorted(seen)  # progress never goes back
            return body
        time.sleep(0.05)
    raise TimeoutError(location)


def test_refine_job_flow_and_idempotent_result(client, scene_id):
    params = {"iterations": 6, "height": 24, "patience": 0}
    r = client.post(f"/v1/scenes/{scene_id}/refine", json=params)
    assert r.status_code == 202, r.text
    location = r.headers["location"]
    assert location.startswith("/v1/jobs/") and r.json()["status"] in ("queued", "running", "done")
    body = _wait(client, location)
    assert body["status"] == "done", body
    assert body["progress"] == 1.0 and body["error"] is None
    new_id = body["scene_id"]
    assert new_id and new_id != scene_id and location == f"/v1/jobs/{new_id}"

    meta = client.get(f"/v1/scenes/{new_id}").json()
    parent = client.get(f"/v1/scenes/{scene_id}").json()
    assert meta["parent"] == scene_id and meta["num_gaussians"] == parent["num_gaussians"]
    assert meta["refine"]["held_loss_best"] <= meta["refine"]["held_loss_start"]
    assert isinstance(meta["refine"]["cross_view_guard"]["accepted"], bool)
    assert client.get(f"/v1/scenes/{new_id}").status_code == 200
    assert can_be_refined_again(client, new_id)
    assert client.get(f"/v1/scenes/{scene_id}").status_code == 200  # the original stays
    img = client.get(f"/v1/scenes/{new_id}/render", params={"c2w": ",".join(map(str, np.eye(4).ravel())),
                                                            "width": 64})
    assert img.status_code == 200

    # same request (defaults spelled out or not): same job, same result, no recomputation
    again = client.post(f"/v1/scenes/{scene_id}/refine", json={**params, "sh_degree": 0})
    assert again.status_code == 202 and again.headers["location"] == location
    assert again.json()["status"] == "done" and again.json()["scene_id"] == new_id
    # a different request gives a different result id
    other = client.post(f"/v1/scenes/{scene_id}/refine", json={**params, "iterations": 3})
    assert other.status_code == 202 and other.headers["location"] != location
    assert _wait(client, other.headers["location"])["status"] == "done"
    # the refined scene keeps its references, so it can be refined again
    chained = client.post(f"/v1/scenes/{new_id}/refine", json={"iterations": 2, "height": 16})
    assert chained.status_code == 202
    assert _wait(client, chained.headers["location"])["status"] == "done"


def test_refine_default_body(client, scene_id):
    r = client.post(f"/v1/scenes/{scene_id}/refine")
    assert r.status_code == 202, r.text
    assert r.headers["location"].startswith("/v1/jobs/")


@pytest.mark.parametrize("body", [
    {"iterations": -1}, {"iterations": 10 ** 6}, {"height": 4}, {"sh_degree": 2}, {"colour_reg": -1},
    {"colour_reg": 0},  # no pull: the Gaussians no reference pixel sees have no equation (the fit did nothing)
    {"holdout": 0.9}, {"iterations": "many"}, {"unknown_option": 1},
    {"holdout": 0, "patience": 5},  # the early stop would watch no held-out pixel: patience would do nothing
])
def test_refine_rejects_bad_options(client, scene_id, body):
    r = client.post(f"/v1/scenes/{scene_id}/refine", json=body)
    assert r.status_code == 422, (body, r.text)
    assert r.json()["error"]["code"] == "invalid_request"


def test_refine_too_large_for_the_render_limit_names_the_height(client, scene_id, live, monkeypatch):
    """A height the schema accepts can still ask for more footprint pixels than one render may: the job fails
    with render_too_large and a message that names the height to lower (not the renderer's internals)."""
    import importlib

    from rasterizer.splat import RenderLimitError
    from service.errors import PayloadTooLarge
    from service.jobs import refine_scene

    def too_large(*a, **k):
        raise RenderLimitError("reduce the image size or the number/size of Gaussians (max_contributions=1)")

    monkeypatch.setattr(importlib.import_module("rasterizer.refine"), "reference_views", too_large)
    with pytest.raises(PayloadTooLarge, match=r"at height 768 .*use a smaller height") as exc:
        refine_scene(live.app.state.store, scene_id, "f" * 32, {"height": 768, "iterations": 1, "holdout": 0.1,
                                                                "sh_degree": 0, "colour_reg": 2.0, "patience": 5})
    assert exc.value.code == "render_too_large" and "max_contributions" not in exc.value.message


def test_unknown_scene_and_job(client):
    r = client.post(f"/v1/scenes/{ZERO_ID}/refine", json={"iterations": 1})
    assert r.status_code == 404 and r.json()["error"]["code"] == "scene_not_found"
    r = client.get(f"/v1/jobs/{ZERO_ID}")
    assert r.status_code == 404 and r.json()["error"]["code"] == "job_not_found"
    assert client.get("/v1/jobs/not-a-job").status_code == 422


def test_registry_dedupes_and_retries_failed():
    reg = JobRegistry()
    job, created = reg.submit("a" * 32, "b" * 32, {"iterations": 1})
    assert created
    same, created2 = reg.submit("a" * 32, "b" * 32, {"iterations": 1})
    assert same is job and not created2
    reg.mark_failed(job, ValueError("boom"))
    assert job.as_json()["error"] == {"code": "ValueError", "message": "boom"}
    retry, created3 = reg.submit("a" * 32, "b" * 32, {"iterations": 1})
    assert created3 and retry is not job and retry.status == "queued"
    report = reg.progress_callback(retry)
    report(0.5)
    report(0.2)
    assert retry.progress == 0.5
    reg.cancel_all()
    with pytest.raises(Exception):
        report(0.6)


def test_result_id_depends_on_everything():
    p = {"iterations": 1}
    base = result_id_for("a" * 32, p, "sha")
    assert base == result_id_for("a" * 32, dict(p), "sha")
    assert base != result_id_for("b" * 32, p, "sha")
    assert base != result_id_for("a" * 32, {"iterations": 2}, "sha")
    assert base != result_id_for("a" * 32, p, "sha2")


def test_registry_reruns_a_done_job_whose_result_is_gone():
    """``done=False`` means the caller found no result scene: a done job is then a new attempt, as a failed one."""
    reg = JobRegistry()
    job, _ = reg.submit("a" * 32, "b" * 32, {})
    reg.mark_done(job)
    assert reg.submit("a" * 32, "b" * 32, {}, done=True) == (job, False)  # the result is stored: the same job
    again, created = reg.submit("a" * 32, "b" * 32, {})
    assert created and again is not job and again.status == "queued"


def test_refine_remakes_its_deleted_result(client, live, scene_id, monkeypatch):
    params = {"iterations": 2, "height": 16, "patience": 0}
    first = client.post(f"/v1/scenes/{scene_id}/refine", json=params)
    assert first.status_code == 202, first.text
    result = _wait(client, first.headers["location"])["scene_id"]
    assert client.delete(f"/v1/scenes/{result}").status_code == 204
    # the job says its scene is gone and how to get it back, and links to no 404
    gone = client.get(first.headers["location"])
    assert gone.status_code == 200 and gone.json()["status"] == "done" and gone.json()["scene_id"] is None
    assert gone.json()["error"]["code"] == "result_removed" and "POST the same refine request" in gone.text
    assert set(gone.json()["links"]) == {"self"}
    # another replica running it again (its job file says so) answers for it, not the stale "removed"
    registry = live.app.state.jobs
    rerun = dataclasses.replace(registry.get(result), status="running", progress=0.25)
    monkeypatch.setattr(registry, "recorded", lambda job_id: rerun if job_id == result else None)
    assert client.get(first.headers["location"]).json()["status"] == "running"
    monkeypatch.undo()
    again = client.post(f"/v1/scenes/{scene_id}/refine", json=params)
    assert again.status_code == 202 and again.json()["status"] in ("queued", "running"), again.text
    assert _wait(client, again.headers["location"])["status"] == "done"
    assert client.get(f"/v1/scenes/{result}").status_code == 200


def _tiny_scene(store, name: str) -> str:
    from rasterizer.gaussians import Gaussians
    from service.store import content_id

    one = np.ones((4, 3), np.float32)
    sid = content_id("jobs-test", name)
    store.put(sid, Gaussians(one, one * 0.1, np.tile([1.0, 0, 0, 0], (4, 1)), np.ones(4), one[:, None]), {})
    return sid


def test_a_queued_job_holds_its_parent_until_it_ends(tmp_path):
    """Another write evicts around a queued job's parent (not only a running one's), and every hold is given back
    however the job ends: cancelled while queued, or failed."""
    import asyncio

    from service.jobs import start_job
    from service.limits import WorkGate
    from service.store import SceneStore

    store = SceneStore(tmp_path, max_scenes=2, budget_bytes=0, min_free_bytes=0)
    parent = _tiny_scene(store, "parent")
    other = _tiny_scene(store, "other")
    store.gaussians(other)  # the parent is now the least recently used scene

    async def scenario() -> None:
        gate = WorkGate("refine", 1, 4, 5)
        await gate.limiter.acquire()  # the one slot is busy: the job waits in the queue
        reg = JobRegistry()
        job, _ = reg.submit("c" * 32, parent, {})
        task = start_job(reg, job, gate, store)
        await asyncio.sleep(0.05)
        assert job.status == "queued" and store.held() == {parent: 1}
        _tiny_scene(store, "result of another job")  # one scene must go: not the queued job's parent
        assert parent in store.ids() and other not in store.ids()
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        assert store.held() == {}
        gate.limiter.release()
        failing, _ = reg.submit("d" * 32, parent, {})  # the parent has no references: this job fails
        await start_job(reg, failing, gate, store)
        assert failing.status == "failed" and store.held() == {}

    asyncio.run(scenario())


def test_refine_on_a_disk_under_the_margin_is_refused_up_front(client, live, scene_id, monkeypatch):
    """As POST /v1/scenes: 507 before any work, and no job accepted (it would run, then fail store_full)."""
    done = client.post(f"/v1/scenes/{scene_id}/refine", json={"iterations": 1, "height": 16})
    assert _wait(client, done.headers["location"])["status"] == "done"
    monkeypatch.setattr(live.app.state.settings, "min_free_store_bytes", 1 << 62)
    jobs = live.app.state.jobs.counts()
    r = client.post(f"/v1/scenes/{scene_id}/refine", json={"iterations": 1, "height": 20})
    assert r.status_code == 507 and "no work was done" in r.json()["error"]["message"], r.text
    assert live.app.state.jobs.counts() == jobs  # no job was made
    again = client.post(f"/v1/scenes/{scene_id}/refine", json={"iterations": 1, "height": 16})
    assert again.status_code == 202 and again.json()["status"] == "done"  # a stored result needs no disk


def test_a_job_cut_by_shutdown_says_so(tmp_path):
    """Queued (its task cancelled as the loop stops) or running (stopped at its next progress report): the job
    fails with a message the client can act on, never a bare 'CancelledError'."""
    import asyncio

    from service.jobs import start_job
    from service.limits import WorkGate
    from service.store import SceneStore

    store = SceneStore(tmp_path, min_free_bytes=0)
    parent = _tiny_scene(store, "parent")
    result = _tiny_scene(store, "result")  # stored: the job's only step is its last progress report

    async def scenario() -> tuple[dict, dict]:
        gate = WorkGate("refine", 1, 4, 5)
        reg = JobRegistry()
        await gate.limiter.acquire()
        queued, _ = reg.submit("e" * 32, parent, {})
        task = start_job(reg, queued, gate, store)
        await asyncio.sleep(0.05)
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        gate.limiter.release()
        running, _ = reg.submit(result, parent, {})
        reg.cancel_all()
        await start_job(reg, running, gate, store)
        return queued.error, running.error

    for error in asyncio.run(scenario()):
        assert error == {"code": "server_shutdown",
                         "message": "the server shut down before the job finished; submit it again"}
    assert store.held() == {}


def test_check_room_refuses_a_result_that_could_not_be_stored_beside_the_held_scenes(tmp_path):
    """With one scene allowed, a refinement's result never fits beside its held parent: refused before it is
    queued (it ran, then failed store_full), nothing evicted; with room it passes."""
    from service.store import SceneStore, StoreFull

    store = SceneStore(tmp_path, max_scenes=1, budget_bytes=0, min_free_bytes=0)
    parent = _tiny_scene(store, "parent")
    with pytest.raises(StoreFull, match="at most 1 scenes"):
        store.check_room(parent, "the refined scene")
    assert store.ids() == [parent] and store.evictions == 0
    roomy = SceneStore(tmp_path / "roomy", max_scenes=2, budget_bytes=0, min_free_bytes=0)
    one, other = _tiny_scene(roomy, "one"), _tiny_scene(roomy, "other")
    roomy.check_room(one, "the refined scene")  # the other scene may be evicted for it: room
    assert sorted(roomy.ids()) == sorted([one, other])  # a check evicts nothing


def test_a_failed_job_names_store_errors_as_the_api_does():
    """A job that fails on the store (its parent deleted before it ran, a full disk) records the code and message the
    API answers that error with, not the Python class and errno text."""
    import errno

    from service.store import SceneNotFound, StoreFull

    reg = JobRegistry()
    job, _ = reg.submit("a" * 32, "b" * 32, {})
    reg.mark_failed(job, SceneNotFound("b" * 32))
    assert job.error == {"code": "scene_not_found", "message": f"no scene with id {'b' * 32!r}"}
    reg.mark_failed(job, OSError(errno.ENOSPC, "No space left on device"))
    assert job.error["code"] == "store_unavailable" and "disk is full" in job.error["message"]
    reg.mark_failed(job, StoreFull("the budget cannot take it"))
    assert job.error == {"code": "store_full", "message": "the budget cannot take it"}


def test_a_holdout_of_zero_alone_takes_the_default_patience_without_complaint():
    """Only a patience the request gives is refused beside holdout 0; the default one (what the request did not
    ask for) stays, unused, as does patience 0."""
    from service.jobs import RefineRequest

    assert RefineRequest.model_validate({"holdout": 0}).patience == 5
    assert RefineRequest.model_validate({"holdout": 0, "patience": 0}).patience == 0
    with pytest.raises(ValueError, match="patience\n.*the early stop watches held-out pixels"):
        RefineRequest.model_validate({"holdout": 0.0, "patience": 1})

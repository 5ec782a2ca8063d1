"""Asynchronous jobs: ``POST /v1/scenes/{id}/refine`` -> 202 + ``Location: /v1/jobs/{job_id}``,
``GET /v1/jobs/{job_id}`` (conventions section 3).

A refined scene is a new scene stored with
``store.put(result_id_for(parent_id, params, model_sha), gaussians, {..., "parent": parent_id})``
(:mod:`service.jobs`); the job id *is* that result id, so the same request on the same scene
answers the same job and, once done, the same scene. The work runs in a background task
through a :class:`service.limits.WorkGate` that shares the inference gate's capacity
limiter (a refinement and a reconstruction never compete for the 2 cores), with its own
bounded queue (503 + Retry-After beyond it).
"""

from __future__ import annotations

from typing import Annotated

import anyio
from fastapi import APIRouter, Body, Path, Request, Response
from pydantic import BaseModel, ConfigDict, Field

from .. import jobs as work
from .. import scenes
from ..deps import KnownQueryParameters, SceneId, SettingsDep, SingleQueryValues, StoreDep, UniqueBodyKeys
from ..errors import Busy, NotFound
from ..job_state import ACTIVE
from ..jobs import RefineRequest
from ..limits import WorkGate
from ..references import ReferencesMissing, has_references
from ..schemas import error_responses
from ..store import SCENE_ID_PATTERN

router = APIRouter(tags=["jobs"], dependencies=[KnownQueryParameters, SingleQueryValues])

class JobStatus(BaseModel):
    model_config = ConfigDict(extra="allow")

    id: str
    status: str = Field(description="queued | running | done | failed")
    progress: float = Field(ge=0.0, le=1.0)
    scene_id: str | None = Field(None, description="the refined scene (a new scene) once done")
    parent_id: str
    error: dict | None = None


def _registry(request: Request) -> work.JobRegistry:
    return request.app.state.jobs


def _gate(request: Request) -> WorkGate:
    return request.app.state.refine_gate


@router.post("/v1/scenes/{scene_id}/refine", status_code=202, response_model=JobStatus, dependencies=[UniqueBodyKeys],
             summary="Refine the colours on the reference views; runs as a job",
             responses=error_responses(404, 409, 415, 422, 503, 507))
async def refine_scene(scene_id: SceneId, request: Request, response: Response, store: StoreDep,
                       settings: SettingsDep,
                       body: Annotated[RefineRequest | None, Body()] = None) -> JobStatus:
    params = (body or RefineRequest()).model_dump()
    if not store.exists(scene_id):
        raise NotFound(f"no scene with id {scene_id!r}", code="scene_not_found")
    if not has_references(store, scene_id):
        raise ReferencesMissing(f"scene {scene_id} has no stored reference images; it cannot be refined")
    model_sha = str((store.meta(scene_id).get("model") or {}).get("sha256") or "")
    job_id = work.result_id_for(scene_id, params, model_sha)
    registry = _registry(request)
    response.headers["Location"] = f"/v1/jobs/{job_id}"
    if store.exists(job_id):
        job, _ = registry.submit(job_id, scene_id, params, done=True)
        return JobStatus(**job.as_json())
    existing = registry.get(job_id)
    if existing is None or existing.status not in ACTIVE:  # failed, or done with its result gone: a new run
        # the result is a new scene: refused before any work when the disk is under the margin (as POST /v1/scenes)
        await anyio.to_thread.run_sync(scenes.check_free_space, store, settings.min_free_store_bytes)
        # and when the store's budget or scene count could not take it beside the scenes jobs hold (507 now, not
        # after the run): the result is about the parent's size
        await anyio.to_thread.run_sync(store.check_room, scene_id, "the refined scene")
        gate = _gate(request)
        if gate.full:
            gate.reject()
            raise Busy(f"refine queue is full; retry in {gate.retry_after} s", retry_after=gate.retry_after)
    job, created = registry.submit(job_id, scene_id, params)
    if created:
        job.task = work.start_job(registry, job, _gate(request), store)
    return JobStatus(**job.as_json())


@router.get("/v1/jobs/{job_id}", response_model=JobStatus, summary="Status of a job",
            responses=error_responses(404, 422))
async def job_status(job_id: Annotated[str, Path(pattern=SCENE_ID_PATTERN)], request: Request,
                     store: StoreDep) -> JobStatus:
    job = _registry(request).get(job_id)
    if job is None:
        if store.exists(job_id):  # finished before a restart: the result is in the store
            meta = store.meta(job_id)
            if meta.get("parent") and meta.get("refine"):  # a refinement's result (not an edit's)
                return JobStatus(id=job_id, status="done", progress=1.0, scene_id=job_id,
                                 parent_id=meta["parent"], error=None)
        raise NotFound(f"no job with id {job_id!r}", code="job_not_found")
    record = job.as_json()
    if job.status == "done" and not await anyio.to_thread.run_sync(store.exists, job_id):
        # done here, but its scene has left the store since (evicted for room, or deleted): another replica
        # may be making it again; else say so, with no link to a 404
        again = await anyio.to_thread.run_sync(_registry(request).recorded, job_id)
        if again is not None and again.status in ACTIVE:
            return JobStatus(**again.as_json())
        record.update(scene_id=None, links={"self": record["links"]["self"]},
                      error={"code": "result_removed",
                             "message": f"the refined scene {job_id} has been removed from the store since the job "
                                        "finished (evicted to make room, or deleted); POST the same refine request "
                                        "to run it again"})
    return JobStatus(**record)

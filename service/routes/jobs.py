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

import asyncio
from typing import Annotated

from fastapi import APIRouter, Body, Path, Request, Response
from pydantic import BaseModel, ConfigDict, Field

from .. import jobs as work
from ..deps import SceneId, StoreDep
from ..errors import Busy, NotFound
from ..job_state import JobFiles, identity
from ..limits import WorkGate
from ..schemas import error_responses
from ..store import SCENE_ID_PATTERN

router = APIRouter(tags=["jobs"])

#: refinement jobs allowed to wait for the (shared) inference capacity
REFINE_QUEUE = 4


class RefineRequest(BaseModel):
    """Options of the +opt refinement (colour/opacity on the reference views, geometry fixed)."""

    model_config = ConfigDict(extra="forbid")

    iterations: int = Field(100, ge=0, le=2000, description="conjugate-gradient steps on colour (or Adam steps "
                                                             "on opacity when optimise_opacity); early-stopped "
                                                             "on held-out reference pixels")
    height: int = Field(128, ge=16, le=1024, description="Yin/Yang working height h (grids h x 3h per reference)")
    sh_degree: int = Field(0, ge=0, le=1, description="0: colour (SH DC) only; 1: also degree-1 SH")
    colour_reg: float = Field(2.0, ge=0.0, le=1e4, description="pull toward the initial colours (relative)")
    optimise_opacity: bool = Field(False, description="also optimise opacity (Adam on logit; slower, "
                                                      "did not help on the dev scenes)")
    opacity_lr: float = Field(0.01, gt=0.0, le=1.0)
    holdout: float = Field(0.1, ge=0.0, le=0.5, description="fraction of reference pixels held out for early stop")
    patience: int = Field(5, ge=0, le=2000, description="stop after this many steps without held-out gain (0: off)")
    cross_check: bool = Field(True, description="cross-view guard: fit each reference alone and score the other; "
                                                "keep the unrefined colours when that gets worse")


class JobStatus(BaseModel):
    model_config = ConfigDict(extra="allow")

    id: str
    status: str = Field(description="queued | running | done | failed")
    progress: float = Field(ge=0.0, le=1.0)
    scene_id: str | None = Field(None, description="the refined scene (a new scene) once done")
    parent_id: str
    error: dict | None = None


def _registry(request: Request) -> work.JobRegistry:
    state = request.app.state
    reg = getattr(state, "jobs", None)
    if reg is None:  # job records beside the scenes: every replica sharing the store answers them
        files = JobFiles(state.store.root / "jobs", identity(state.settings.replica_id))
        reg = state.jobs = work.JobRegistry(files=files)
    return reg


def _gate(request: Request) -> WorkGate:
    state = request.app.state
    gate = getattr(state, "refine_gate", None)
    if gate is None:
        s = state.settings
        gate = WorkGate("refine", s.inference_concurrency, REFINE_QUEUE, s.retry_after_s)
        gate.limiter = state.inference_gate.limiter  # share the CPU budget with inference
        state.refine_gate = gate
    return gate


@router.post("/v1/scenes/{scene_id}/refine", status_code=202, response_model=JobStatus,
             summary="Refine colour and opacity on the reference views (+opt); runs as a job",
             responses=error_responses(404, 409, 422, 503))
async def refine_scene(scene_id: SceneId, request: Request, response: Response, store: StoreDep,
                       body: Annotated[RefineRequest | None, Body()] = None) -> JobStatus:
    params = (body or RefineRequest()).model_dump()
    if not store.exists(scene_id):
        raise NotFound(f"no scene with id {scene_id!r}", code="scene_not_found")
    if not work.has_references(store, scene_id):
        raise work.ReferencesMissing(f"scene {scene_id} has no stored reference images; it cannot be refined")
    model_sha = str((store.meta(scene_id).get("model") or {}).get("sha256") or "")
    job_id = work.result_id_for(scene_id, params, model_sha)
    registry = _registry(request)
    response.headers["Location"] = f"/v1/jobs/{job_id}"
    if store.exists(job_id):
        job, _ = registry.submit(job_id, scene_id, params, done=True)
        return JobStatus(**job.as_json())
    existing = registry.get(job_id)
    if existing is None or existing.status == "failed":
        gate = _gate(request)
        if gate.admitted >= gate.concurrency + gate.queue:
            raise Busy(f"refine queue is full; retry in {gate.retry_after} s", retry_after=gate.retry_after)
    job, created = registry.submit(job_id, scene_id, params)
    if created:
        job.task = asyncio.get_running_loop().create_task(work.run_job(registry, job, _gate(request), store))
    return JobStatus(**job.as_json())


@router.get("/v1/jobs/{job_id}", response_model=JobStatus, summary="Status of a job",
            responses=error_responses(404, 422))
async def job_status(job_id: Annotated[str, Path(pattern=SCENE_ID_PATTERN)], request: Request,
                     store: StoreDep) -> JobStatus:
    job = _registry(request).get(job_id)
    if job is None:
        if store.exists(job_id):  # finished before a restart: the result is in the store
            meta = store.meta(job_id)
            if meta.get("parent"):
                return JobStatus(id=job_id, status="done", progress=1.0, scene_id=job_id,
                                 parent_id=meta["parent"], error=None)
        raise NotFound(f"no job with id {job_id!r}", code="job_not_found")
    return JobStatus(**job.as_json())

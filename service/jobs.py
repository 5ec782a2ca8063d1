"""Refinement jobs, independent of HTTP: the blocking work and an in-memory job registry.

* :func:`refine_scene` (blocking, runs in a worker thread): load a stored scene and its
  reference images, refine the colours (:mod:`rasterizer.refine`), store the result
  as a *new* scene ``result_id`` (atomic ``store.put``; the parent stays) with
  ``meta["parent"] = parent_id``, and copy the references to it so it can be refined again.
* :class:`JobRegistry`: jobs keyed by their result id (``job_id == result scene id``, the
  content hash of parent id + canonical params + model sha256), so the same request on the
  same scene maps to the same job and the same result. Given :class:`service.job_state.JobFiles`,
  every state change (and a heartbeat) is also written to the store, so any replica sharing
  it answers the job; one whose owner died is reported ``failed`` (``replica_lost``), never
  ``running`` forever. The store never holds a half-written scene, and a finished job is
  still answered as ``done`` from the store.

Reference images: a scene must carry the artifact ``references.npz`` (uint8 ERP arrays
``image_a``, ``image_b``, H x 2H x 3, as fed to the encoder); poses come from
``meta["poses"]["c2w"]`` (OpenCV). Scene creation stores it with the scene
(:mod:`service.references`).
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any, Callable

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator

from rasterizer.splat import RenderLimitError

from .edits import EDIT_ARTIFACT
from .errors import PayloadTooLarge, translate
from .job_state import ACTIVE, HEARTBEAT_S, JobFiles
from .memory import release_memory
from .references import REFERENCES_ARTIFACT, load_references, references_artifact
from .store import SceneNotFound, SceneStore, canonical_json, content_id

log = logging.getLogger("omnisplat.jobs")

REFINE_VERSION = "refine/v2"  # v2: cross-view guard (same params, different result)
#: finished jobs kept in memory (oldest dropped first)
MAX_FINISHED_JOBS = 1000
#: refinement jobs allowed to wait for the (shared) inference capacity
REFINE_QUEUE = 4
#: least seconds between two progress writes of one job to its job file
PROGRESS_WRITE_S = 0.5


class RefineRequest(BaseModel):
    """Options of the refinement (colour on the reference views, geometry fixed); strict types."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)

    iterations: int = Field(100, ge=0, le=2000, description="conjugate-gradient steps on colour; early-stopped "
                                                             "on held-out reference pixels")
    height: int = Field(128, ge=16, le=1024, description="Yin/Yang working height h (grids h x 3h per reference)")
    sh_degree: int = Field(0, ge=0, le=1, description="0: colour (SH DC) only; 1: also degree-1 SH")
    colour_reg: float = Field(2.0, gt=0.0, le=1e4, description="pull toward the initial colours (relative; > 0: "
                              "a Gaussian no reference pixel sees is held by it alone)")
    holdout: float = Field(0.1, ge=0.0, le=0.5, description="fraction of reference pixels held out for early stop")
    patience: int = Field(5, ge=0, le=2000, description="stop after this many steps without held-out gain (0: off)")
    cross_check: bool = Field(True, description="cross-view guard: fit each reference alone and score the other; "
                                                "keep the unrefined colours when that gets worse")

    @field_validator("patience")
    @classmethod
    def _patience_needs_a_holdout(cls, patience: int, info: ValidationInfo) -> int:
        """A ``patience`` the request gives (the default is not checked) beside ``holdout`` 0 is refused, as
        parameters a request would not use are: the early stop watches the held-out pixels, and there are none."""
        if patience > 0 and info.data.get("holdout") == 0:
            raise ValueError("the early stop watches held-out pixels and holdout 0 holds none out; give holdout > 0, "
                             "or leave patience out")
        return patience


class JobCancelled(Exception):
    """A job cut by the service's shutdown: raised inside its progress callback when the registry is shutting
    down, and recorded (with this code and message) for a job whose task was cancelled, queued or running."""

    code = "server_shutdown"
    message = "the server shut down before the job finished; submit it again"

    def __init__(self) -> None:
        super().__init__(self.message)


def result_id_for(parent_id: str, params: dict, model_sha256: str) -> str:
    """Id of the refined scene: same parent + params + model, same id."""
    return content_id(REFINE_VERSION, parent_id, canonical_json(params), model_sha256 or "")


def refine_scene(store: SceneStore, parent_id: str, result_id: str, params: dict,
                 progress: Callable[[float], None] | None = None) -> dict:
    """Refine ``parent_id`` with ``params`` and store it as ``result_id``; returns the new scene's meta.

    ``params``: iterations, height (Yin/Yang working height), sh_degree, colour_reg, holdout,
    patience, cross_check (see :class:`rasterizer.refine.RefineOptions`; the rest keep its defaults).
    """
    report = progress or (lambda f: None)
    if store.exists(result_id):
        report(1.0)
        return store.meta(result_id)
    with store.hold(parent_id):  # the budget never evicts the scene being refined
        try:
            return _refine(store, parent_id, result_id, params, report)
        except RenderLimitError:
            h = int(params["height"])
            raise PayloadTooLarge(f"refine: at height {h} (Yin and Yang grids {h}x{3 * h} per reference) this scene's "
                                  "Gaussians cover more pixels than one render may; use a smaller height",
                                  code="render_too_large") from None


def _refine(store: SceneStore, parent_id: str, result_id: str, params: dict, report: Callable[[float], None]) -> dict:
    from rasterizer.refine import RefineOptions, reference_views, refine

    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    parent_meta = store.meta(parent_id)
    gaussians = store.gaussians(parent_id)
    # read once, now: the result keeps them even when the parent is deleted while the job runs
    references = references_artifact(store, parent_id)
    # geometry, count and order of the Gaussians stay: the parent's correspondences hold for the result
    correspondences = store.artifact(parent_id, EDIT_ARTIFACT)
    artifacts = {REFERENCES_ARTIFACT: references}
    if correspondences is not None:
        try:
            artifacts[EDIT_ARTIFACT] = correspondences.read_bytes()
        except FileNotFoundError:  # the parent was deleted meanwhile
            raise SceneNotFound(parent_id) from None
    images, c2ws = load_references(store, parent_id)
    timings["load"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    views = reference_views(gaussians, images, c2ws, height=int(params["height"]),
                            holdout=float(params["holdout"]), seed=0)
    timings["footprints"] = time.perf_counter() - t1
    report(0.1)
    opts = RefineOptions(iterations=int(params["iterations"]), sh_degree=int(params["sh_degree"]),
                         colour_reg=float(params["colour_reg"]), patience=int(params["patience"]),
                         cross_check=bool(params.get("cross_check", True)))
    t1 = time.perf_counter()
    result = refine(gaussians, views, opts, progress=lambda f: report(0.1 + 0.85 * f))
    timings["refine"] = time.perf_counter() - t1
    first, last = result.history[0], result.history[-1]
    meta = {k: v for k, v in parent_meta.items() if k not in ("id", "num_gaussians", "created_at", "links")}
    meta.update({
        "parent": parent_id,
        "refine": {"params": params, "best_iteration": result.best_iteration,
                   "iterations_run": last["iteration"], "held_loss_start": first["held_loss"],
                   "held_loss_best": min((h["held_loss"] for h in result.history if h["held_loss"] is not None),
                                         default=None),
                   "cross_view_guard": None if result.cross is None else {
                       "accepted": bool(result.cross.get("accepted")),
                       "seconds": result.cross.get("seconds")},
                   "version": REFINE_VERSION},
        "created_at": time.time(),
    })
    t1 = time.perf_counter()
    timings["total"] = time.perf_counter() - t0
    meta["timings"] = timings
    if len(result.gaussians) != len(gaussians):  # the correspondences index the parent's Gaussians
        artifacts.pop(EDIT_ARTIFACT, None)
    stored = store.put(result_id, result.gaussians, meta, artifacts=artifacts)
    report(1.0)
    return stored


@dataclass
class Job:
    """One refinement job; ``id`` is also the id the refined scene gets."""

    id: str
    parent_id: str
    params: dict
    status: str = "queued"  # queued | running | done | failed
    progress: float = 0.0
    error: dict | None = None
    created_at: float = field(default_factory=time.time)
    started_at: float | None = None
    finished_at: float | None = None
    owner: dict | None = None  # host, pid, replica of the process running it (with job files)
    task: Any = field(default=None, repr=False)

    def as_json(self) -> dict:
        done = self.status == "done"
        return {"id": self.id, "status": self.status, "progress": round(float(self.progress), 4),
                "scene_id": self.id if done else None, "parent_id": self.parent_id, "params": self.params,
                "error": self.error, "created_at": self.created_at, "started_at": self.started_at,
                "finished_at": self.finished_at, **({"owner": self.owner} if self.owner else {}),
                "links": {"self": f"/v1/jobs/{self.id}", **({"scene": f"/v1/scenes/{self.id}"} if done else {})}}

    @classmethod
    def from_record(cls, record: dict) -> "Job":
        """A read-only snapshot of a job file written by any replica."""
        return cls(record["id"], record["parent_id"], record.get("params") or {}, record["status"],
                   float(record.get("progress") or 0.0), record.get("error"), record.get("created_at") or 0.0,
                   record.get("started_at"), record.get("finished_at"), record.get("owner"))


class JobRegistry:
    """Thread-safe jobs (progress is written from worker threads); shared through ``files`` when given."""

    def __init__(self, max_finished: int = MAX_FINISHED_JOBS, files: JobFiles | None = None) -> None:
        self._jobs: OrderedDict[str, Job] = OrderedDict()
        self._lock = threading.Lock()
        self.max_finished = max_finished
        self.cancelled = threading.Event()
        self.files = files
        self._saved: dict[str, float] = {}  # job id -> time of its last write (progress throttle)
        self._heartbeat: threading.Thread | None = None

    def get(self, job_id: str) -> Job | None:
        """This process's job, else the one another replica recorded (``failed`` if its owner died)."""
        with self._lock:
            job = self._jobs.get(job_id)
        return job if job is not None else self.recorded(job_id)

    def recorded(self, job_id: str) -> Job | None:
        """The job as the job files record it (another replica's, or this one's last write); None without them."""
        record = self.files.read(job_id) if self.files is not None else None
        if record is None:
            return None
        job = Job.from_record(record)
        reason = self.files.lost(record)
        if reason is not None:
            job.status, job.finished_at = "failed", record.get("heartbeat")
            job.error = {"code": "replica_lost", "message": reason}
        return job

    def _save(self, job: Job) -> None:
        if self.files is None:
            return
        self._saved[job.id] = time.monotonic()
        try:
            self.files.write(job.as_json())
        except OSError as exc:  # a full or briefly unreachable volume: this replica still answers; next write retries
            log.warning("job %s: job file not written (%s)", job.id, exc)

    def _beat(self) -> None:
        while not self.cancelled.wait(HEARTBEAT_S):
            with self._lock:
                active = [j for j in self._jobs.values() if j.status in ACTIVE]
            for job in active:
                self._save(job)

    def submit(self, job_id: str, parent_id: str, params: dict, *, done: bool = False) -> tuple[Job, bool]:
        """The job for ``job_id``: an existing queued/running/done one, else a new one (created=True).

        ``done=True`` records an already stored result. A failed job is replaced by a new attempt, and
        so is a done one when ``done=False``: the caller found its result scene gone (deleted or evicted),
        so the same request makes it again instead of answering a scene that no longer exists.
        """
        with self._lock:
            job = self._jobs.get(job_id)
            if job is not None and (job.status in ACTIVE or (job.status == "done" and done)):
                return job, False
            if not done:
                other = self.recorded(job_id)  # queued/running on another replica
                if other is not None and other.status in ACTIVE:
                    return other, False
            job = Job(job_id, parent_id, params, owner=self.files.owner if self.files is not None else None)
            if done:
                job.status, job.progress, job.finished_at = "done", 1.0, time.time()
            self._jobs[job_id] = job
            self._jobs.move_to_end(job_id)
            self._trim()
            if self.files is not None and not done and self._heartbeat is None:
                self._heartbeat = threading.Thread(target=self._beat, name="job-heartbeat", daemon=True)
                self._heartbeat.start()
        self._save(job)
        return job, not done

    def _trim(self) -> None:
        finished = [k for k, j in self._jobs.items() if j.status in ("done", "failed")]
        for k in finished[: max(0, len(finished) - self.max_finished)]:
            del self._jobs[k]
            self._saved.pop(k, None)

    def progress_callback(self, job: Job) -> Callable[[float], None]:
        def report(fraction: float) -> None:
            if self.cancelled.is_set():
                raise JobCancelled()
            job.progress = float(min(1.0, max(job.progress, fraction)))
            if time.monotonic() - self._saved.get(job.id, 0.0) >= PROGRESS_WRITE_S:
                self._save(job)
        return report

    def mark_running(self, job: Job) -> None:
        job.status, job.started_at = "running", time.time()
        self._save(job)

    def mark_done(self, job: Job) -> None:
        job.status, job.progress, job.finished_at = "done", 1.0, time.time()
        self._save(job)

    def mark_failed(self, job: Job, exc: BaseException) -> None:
        """Record ``exc`` on the job: a store or domain error with the code and message the API answers it with
        (:func:`service.errors.translate`: ``scene_not_found``, ``store_unavailable``...), anything else by its
        class name and text."""
        if isinstance(exc, Exception):
            exc = translate(exc)
        code = getattr(exc, "code", None) or type(exc).__name__
        message = getattr(exc, "message", None) or str(exc) or type(exc).__name__
        job.status, job.error, job.finished_at = "failed", {"code": code, "message": message}, time.time()
        self._save(job)

    def cancel_all(self) -> None:
        """Make running jobs stop at their next progress report (service shutdown)."""
        self.cancelled.set()

    def counts(self) -> dict[str, int]:
        with self._lock:
            out = {s: 0 for s in ("queued", "running", "done", "failed")}
            for j in self._jobs.values():
                out[j.status] += 1
            return out


def start_job(registry: JobRegistry, job: Job, gate, store: SceneStore) -> asyncio.Task:
    """Start :func:`run_job` as a task on the running loop; the job's parent is held from now (queued
    included) until the task ends, whatever the outcome (done, failed, cancelled even before it started):
    another job's result never evicts the scene an accepted job waits to refine."""
    store.acquire(job.parent_id)
    try:
        task = asyncio.get_running_loop().create_task(run_job(registry, job, gate, store))
    except BaseException:
        store.release(job.parent_id)
        raise
    task.add_done_callback(lambda _: store.release(job.parent_id))
    return task


async def run_job(registry: JobRegistry, job: Job, gate, store: SceneStore) -> None:
    """Run one job through ``gate`` (a WorkGate); every outcome lands in the job record."""
    report = registry.progress_callback(job)

    def work() -> dict:
        registry.mark_running(job)
        try:
            return refine_scene(store, job.parent_id, job.id, job.params, report)  # StoreFull: a 507 saying which limit
        finally:
            release_memory(force=True)

    try:
        await gate.run(work)
    except asyncio.CancelledError:  # the loop stops (graceful shutdown): say so, not "CancelledError"
        registry.mark_failed(job, JobCancelled())
        raise
    except BaseException as exc:  # noqa: BLE001 - recorded on the job; KeyboardInterrupt and such re-raised
        registry.mark_failed(job, exc)
        if not isinstance(exc, Exception):
            raise
        return
    registry.mark_done(job)

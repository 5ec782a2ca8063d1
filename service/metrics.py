"""Prometheus metrics of one app instance (own registry, so several apps can live in one process).

Exposed at ``GET /metrics``: request counts and latencies by route template, method and
status; seconds per pipeline stage (decode, the encoder's stages, store, render, encode);
scenes stored, their bytes against the store budget, evictions and refused writes; work in flight /
waiting / rejected; scene-cache hits and misses; build info.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.exposition import CONTENT_TYPE_LATEST

if TYPE_CHECKING:
    from .limits import WorkGate
    from .store import SceneStore

_LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60, 120)


class ServiceMetrics:
    def __init__(self) -> None:
        self.registry = r = CollectorRegistry()
        self.requests = Counter("omnisplat_http_requests_total", "HTTP requests",
                                ["route", "method", "status"], registry=r)
        self.latency = Histogram("omnisplat_http_request_duration_seconds", "HTTP request latency",
                                 ["route", "method", "status"], buckets=_LATENCY_BUCKETS, registry=r)
        self.stage = Histogram("omnisplat_stage_seconds", "Seconds per pipeline stage", ["stage"],
                               buckets=_LATENCY_BUCKETS, registry=r)
        self.scenes_stored = Gauge("omnisplat_scenes_stored", "Scenes in the on-disk store", registry=r)
        self.scenes_created = Counter("omnisplat_scenes_created_total", "Scenes reconstructed", registry=r)
        self.in_flight = Gauge("omnisplat_work_in_flight", "Jobs running", ["kind"], registry=r)
        self.waiting = Gauge("omnisplat_work_waiting", "Jobs waiting for a worker", ["kind"], registry=r)
        self.rejected = Counter("omnisplat_work_rejected_total", "Jobs refused with 503", ["kind"], registry=r)
        self.cache_hits = Gauge("omnisplat_scene_cache_hits", "Scene cache hits since start", registry=r)
        self.cache_misses = Gauge("omnisplat_scene_cache_misses", "Scene cache misses since start", registry=r)
        self.cache_bytes = Gauge("omnisplat_scene_cache_bytes", "Bytes held by the scene cache", registry=r)
        self.store_bytes = Gauge("omnisplat_store_bytes", "Bytes the stored scenes take on disk", registry=r)
        self.store_budget = Gauge("omnisplat_store_budget_bytes", "Store budget in bytes (0: no cap)", registry=r)
        self.store_evictions = Gauge("omnisplat_store_evictions", "Scenes evicted for the budget since start",
                                     registry=r)
        self.store_refusals = Gauge("omnisplat_store_refusals", "Writes refused by the budget or the free-space "
                                    "margin since start", registry=r)
        self.body_rejected = Counter("omnisplat_upload_rejected_total", "Bodies refused with 413", registry=r)
        self.build = Gauge("omnisplat_build_info", "Model loaded (value 1)",
                           ["model_name", "model_version", "model_sha256"], registry=r)
        self.ready = Gauge("omnisplat_ready", "1 once the model is loaded and warmed up", registry=r)

    def observe_stages(self, timings: dict[str, float]) -> None:
        for stage, seconds in timings.items():
            try:
                value = float(seconds)
            except (TypeError, ValueError):
                continue
            if value >= 0:
                self.stage.labels(stage=str(stage)).observe(value)

    def render(self, store: "SceneStore | None", gates: "list[WorkGate]") -> tuple[bytes, str]:
        if store is not None:
            self.scenes_stored.set(store.count())
            self.cache_hits.set(store.cache.hits)
            self.cache_misses.set(store.cache.misses)
            self.cache_bytes.set(store.cache.nbytes)
            self.store_bytes.set(store.usage())
            self.store_budget.set(store.budget_bytes)
            self.store_evictions.set(store.evictions)
            self.store_refusals.set(store.refusals)
        for gate in gates:
            self.in_flight.labels(kind=gate.name).set(gate.running)
            self.waiting.labels(kind=gate.name).set(gate.waiting)
        return generate_latest(self.registry), CONTENT_TYPE_LATEST


class RequestMetrics:
    """ASGI middleware recording count and latency per route template (not per raw path)."""

    def __init__(self, app, metrics: ServiceMetrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = {"code": 500}

        async def send_wrapper(message):
            if message["type"] == "http.response.start":
                status["code"] = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            route = scope.get("route")
            path = getattr(route, "path", None) or "unmatched"
            labels = {"route": path, "method": scope.get("method", ""), "status": str(status["code"])}
            self.metrics.requests.labels(**labels).inc()
            self.metrics.latency.labels(**labels).observe(time.perf_counter() - start)

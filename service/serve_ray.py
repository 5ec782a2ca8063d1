"""``omnisplat serve --ray``: the same app (:func:`service.app.create_app`) on Ray Serve replicas.

Each replica builds its own app when it starts (``__serve_build_asgi_app__``), so the lifespan
(model load, work gates, job registry) runs per replica, with ``ort_threads`` = the replica's
``num_cpus`` and its own queue limits (503 beyond them). Ray Serve's proxy spreads requests and
autoscales between ``min_replicas`` and ``max_replicas``. Replicas share the store directory:
scenes (content-hash ids, atomic writes) and job records (:mod:`service.job_state`); on a
cluster that directory is a ReadWriteMany volume. Ray is imported only inside functions
(``pip install .[ray]``).
"""

from __future__ import annotations

import signal
import sys
import time
from dataclasses import dataclass, fields

from .config import Settings

#: response header naming the replica that answered: ``<replica id> <host>:<pid>``
REPLICA_HEADER = "x-omnisplat-replica"
#: unfinished store writes younger than this survive a replica's start-up (another one may be writing them)
SHARED_TMP_GRACE_S = 600.0
#: requests the Serve proxy holds for the deployment before it answers 503 itself
MAX_QUEUED_REQUESTS = 64


@dataclass(frozen=True)
class RayOptions:
    """Replica count, size and autoscaling target."""

    min_replicas: int = 1
    max_replicas: int = 2
    replica_cpus: float = 1.0
    target_ongoing_requests: float = 2.0


def deployment_options(settings: Settings, opts: RayOptions) -> dict:
    """``serve.deployment`` keyword arguments; a replica takes what its own gates admit, plus status reads."""
    admitted = (settings.inference_concurrency + settings.inference_queue
                + settings.render_concurrency + settings.render_queue)
    return {
        "name": "omnisplat",
        "ray_actor_options": {"num_cpus": opts.replica_cpus},
        "max_ongoing_requests": admitted + 8,  # + job status / health / metadata reads, which are cheap
        "max_queued_requests": MAX_QUEUED_REQUESTS,
        "autoscaling_config": {"min_replicas": opts.min_replicas, "max_replicas": opts.max_replicas,
                               "initial_replicas": opts.min_replicas,
                               "target_ongoing_requests": opts.target_ongoing_requests,
                               "upscale_delay_s": 10.0, "downscale_delay_s": 120.0},
        "health_check_period_s": 10.0,
        "graceful_shutdown_timeout_s": 20.0,
    }


def replica_settings(config: dict, replica_cpus: float, replica_id: str) -> Settings:
    """A replica's settings: the deployment's, with onnxruntime threads = its CPUs and its own name."""
    return Settings(**{**config, "ort_threads": max(1, int(replica_cpus)), "replica_id": replica_id,
                       "store_tmp_grace_s": max(float(config.get("store_tmp_grace_s") or 0.0), SHARED_TMP_GRACE_S)})


class ReplicaHeader:
    """ASGI middleware: every response names the replica (and process) that answered it."""

    def __init__(self, app, value: str) -> None:
        self.app, self.value = app, value.encode()

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)

        async def named_send(message):
            if message["type"] == "http.response.start":
                message = {**message, "headers": [*message.get("headers", []), (REPLICA_HEADER.encode(), self.value)]}
            await send(message)

        await self.app(scope, receive, named_send)


def replica_app(settings: Settings):
    """The app one replica serves: :func:`create_app` plus the replica header."""
    from .app import create_app
    from .job_state import identity

    me = identity(settings.replica_id)
    app = create_app(settings)
    app.add_middleware(ReplicaHeader, value=f"{me['replica']} {me['host']}:{me['pid']}")
    return app


def model_error(app) -> str | None:
    """Why this app's model failed to load (None while loading or once ready)."""
    runtime = getattr(getattr(app, "state", None), "runtime", None)
    return getattr(runtime, "error", None)


def build(settings: Settings, opts: RayOptions):
    """The bound Ray Serve application (needs ``ray[serve]``)."""
    from ray import serve

    @serve.ingress()
    class Omnisplat:
        def __init__(self, config: dict) -> None:
            replica = serve.get_replica_context().replica_id.unique_id
            self.settings = replica_settings(config, opts.replica_cpus, replica)

        def __serve_build_asgi_app__(self):
            self.omnisplat_app = replica_app(self.settings)
            return self.omnisplat_app

        def check_health(self) -> None:
            """Ray's health check: a replica whose model failed to load is replaced."""
            failed = model_error(getattr(self, "omnisplat_app", None))
            if failed:
                raise RuntimeError(f"model failed to load: {failed}")

    config = settings.model_dump(mode="json", exclude={"resolved_model_path"})
    return serve.deployment(**deployment_options(settings, opts))(Omnisplat).bind(config)


def app_builder(args: dict):
    """``serve run service.serve_ray:app_builder min_replicas=2 ...`` and KubeRay's ``serveConfigV2`` import path.

    Settings come from ``OMNISPLAT_*`` variables; ``args`` (strings allowed) set :class:`RayOptions`.
    """
    cast = {"int": int, "float": float}
    opts = RayOptions(**{f.name: cast[str(f.type)](args[f.name]) for f in fields(RayOptions) if f.name in args})
    return build(Settings(), opts)


def run(settings: Settings, opts: RayOptions, address: str | None = None) -> int:
    """Start (or join, with ``address``) a Ray cluster, deploy on its Serve proxy and block until Ctrl-C."""
    import ray
    from ray import serve

    if address is None:
        ray.init(include_dashboard=False)  # a local one-machine cluster, stopped with this process
    else:
        ray.init(address=address)
    # one proxy (on the head): on one machine, a proxy per node would contend for the same port
    serve.start(http_options={"host": settings.host, "port": settings.port}, proxy_location="HeadOnly")
    serve.run(build(settings, opts), name="omnisplat", route_prefix="/")
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:  # Ctrl-C or SIGTERM: the application goes with this command (as with `serve run`)
        serve.delete("omnisplat")
    return 0

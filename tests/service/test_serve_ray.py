"""The Ray Serve module without Ray: options, per-replica settings, the replica header, the CLI's error.

Ray itself (replicas, the proxy, kill -9 of a replica) is exercised by scripts/ray-scale-test.sh.
"""

from __future__ import annotations

import sys

import anyio
import httpx
import pytest
from fastapi import FastAPI

from service import cli
from service.config import Settings
from service.serve_ray import (
    REPLICA_HEADER,
    SHARED_TMP_GRACE_S,
    RayOptions,
    ReplicaHeader,
    deployment_options,
    model_error,
    replica_settings,
)


def test_deployment_options_follow_settings_and_options():
    s = Settings(inference_concurrency=1, inference_queue=2, render_concurrency=1, render_queue=4)
    opts = deployment_options(s, RayOptions(min_replicas=2, max_replicas=5, replica_cpus=2, target_ongoing_requests=3))
    assert opts["ray_actor_options"] == {"num_cpus": 2}
    assert opts["autoscaling_config"]["min_replicas"] == 2 and opts["autoscaling_config"]["max_replicas"] == 5
    assert opts["autoscaling_config"]["target_ongoing_requests"] == 3
    assert opts["max_ongoing_requests"] > 1 + 2 + 1 + 4  # our own gates answer 503 before Ray queues


def test_replica_settings_take_the_replica_cpus_and_name(tmp_path):
    config = Settings(store_dir=tmp_path, ort_threads=8).model_dump(mode="json", exclude={"resolved_model_path"})
    s = replica_settings(config, 1.0, "abc123")
    assert (s.ort_threads, s.replica_id, s.store_dir) == (1, "abc123", tmp_path)
    assert s.store_tmp_grace_s == SHARED_TMP_GRACE_S
    assert replica_settings(config, 3.0, "x").ort_threads == 3


def test_replica_header_names_the_answering_process():
    app = FastAPI()

    @app.get("/x")
    async def x() -> dict:
        return {"ok": True}

    named = ReplicaHeader(app, "r1 host:42")

    async def get():
        async with httpx.AsyncClient(transport=httpx.ASGITransport(app=named), base_url="http://t") as c:
            return await c.get("/x")

    r = anyio.run(get)
    assert r.status_code == 200 and r.headers[REPLICA_HEADER] == "r1 host:42" and r.json() == {"ok": True}


def test_serve_ray_without_ray_is_a_clear_error(tmp_path, monkeypatch, capsys):
    model = tmp_path / "m.onnx"
    model.write_bytes(b"not loaded")
    monkeypatch.setitem(sys.modules, "ray", None)  # as if the [ray] extra were not installed
    assert cli.main(["serve", "--ray", "--model", str(model), "--store", str(tmp_path / "s")]) == 2
    assert "pip install 'omnisplat[ray]'" in capsys.readouterr().err


@pytest.mark.parametrize("flag", ["--ray", "--ray-address", "--min-replicas", "--max-replicas", "--replica-cpus"])
def test_serve_help_lists_the_ray_flags(flag, capsys):
    with pytest.raises(SystemExit):
        cli.main(["serve", "--help"])
    assert flag in capsys.readouterr().out


def test_model_error_is_what_ray_health_checks_see():
    app = FastAPI()
    assert model_error(app) is None  # lifespan not run yet
    app.state.runtime = type("R", (), {"error": None})()
    assert model_error(app) is None
    app.state.runtime.error = "InvalidProtobuf: bad model"
    assert model_error(app) == "InvalidProtobuf: bad model"

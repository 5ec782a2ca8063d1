"""What the Docker runtime stage does, without Docker: a fresh venv with only the runtime
install step (``pip install .``: runtime dependencies, no torch) serves a prebuilt model.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import plyfile
import pytest

from tests.service._support import IDENTITY, POSES, panorama, small_model

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_runtime_only_venv_serves_prebuilt_model(tmp_path_factory, tmp_path):
    model = small_model(tmp_path_factory)
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    py = venv / "bin" / "python"
    # the Dockerfile's runtime stage: copy what it copies, then `pip install .`
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    for pkg in ("rasterizer", "service"):
        shutil.copytree(ROOT / pkg, src / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    (src / "export").mkdir()
    shutil.copy(ROOT / "export" / "__init__.py", src / "export" / "__init__.py")
    install = subprocess.run([str(py), "-m", "pip", "install", "-q", "--disable-pip-version-check", str(src)],
                             capture_output=True, text=True, timeout=900)
    assert install.returncode == 0, install.stdout[-3000:] + install.stderr[-3000:]
    no_torch = subprocess.run([str(py), "-c",
                               "import importlib.util, sys; sys.exit(importlib.util.find_spec('torch') is not None)"],
                              cwd=tmp_path, timeout=60)
    assert no_torch.returncode == 0, "torch must not be installed by the runtime dependencies"

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {k: v for k, v in os.environ.items() if not k.startswith("OMNISPLAT_")}
    env.update(OMNISPLAT_PORT=str(port), OMNISPLAT_STORE_DIR=str(tmp_path / "scenes"), PYTHONPATH="")
    # run from a neutral folder so the installed package, not the checkout, is imported
    server = subprocess.Popen([str(venv / "bin" / "omnisplat"), "serve", "--no-build", "--model", str(model),
                               "--log-level", "warning"], cwd=tmp_path, env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline:
            assert server.poll() is None, server.stdout.read()
            try:
                if httpx.get(url + "/healthz", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                time.sleep(0.2)
        assert httpx.get(url + "/healthz").json() == {"status": "ok"}
        while httpx.get(url + "/readyz").status_code != 200:
            assert time.monotonic() < deadline and server.poll() is None
            time.sleep(0.2)
        with httpx.Client(base_url=url, timeout=120) as c:
            # every endpoint the runtime serves, +opt refinement (scipy) included
            r = c.post("/v1/scenes", files={"image_a": ("a.png", panorama(seed=1)),
                                            "image_b": ("b.png", panorama(seed=2))}, data={"poses": POSES})
            assert r.status_code == 201, r.text
            sid, n = r.json()["id"], r.json()["num_gaussians"]
            render = c.get(f"/v1/scenes/{sid}/render", params={"c2w": IDENTITY, "width": 64})
            assert render.status_code == 200 and render.headers["content-type"] == "image/png"
            ply = c.get(f"/v1/scenes/{sid}/gaussians.ply")
            assert ply.status_code == 200 and plyfile.PlyData.read(io.BytesIO(ply.content))["vertex"].count == n
            assert c.get(f"/v1/scenes/{sid}").json()["num_gaussians"] == n
            job = c.post(f"/v1/scenes/{sid}/refine", json={"iterations": 3, "height": 32})
            assert job.status_code == 202, job.text
            while (status := c.get(job.headers["location"]).json())["status"] in ("queued", "running"):
                assert time.monotonic() < deadline + 300
                time.sleep(0.2)
            assert status["status"] == "done", status
            refined = status["scene_id"]
            assert c.get(f"/v1/scenes/{refined}").json()["parent"] == sid
            assert c.get(f"/v1/scenes/{refined}/render", params={"c2w": IDENTITY, "width": 64}).status_code == 200
            for gone in (refined, sid):
                assert c.delete(f"/v1/scenes/{gone}").status_code == 204
                assert c.get(f"/v1/scenes/{gone}").status_code == 404
            assert c.get("/readyz").json()["ready"] is True
            assert "omnisplat_scenes_created_total" in c.get("/metrics").text
            info = c.get("/v1/info")
            assert info.json()["model"]["sha256"] and "path" not in info.json()["model"]
            assert str(tmp_path) not in info.text  # no server paths
            modules = subprocess.run([str(py), "-c", "import json, sys, service.app, service.cli; "
                                      "print(json.dumps([service.app.__file__, 'torch' in sys.modules]))"],
                                     cwd=tmp_path, capture_output=True, text=True, env=env, timeout=60)
            where, torch_loaded = json.loads(modules.stdout)
            assert str(venv) in where and not torch_loaded
    finally:
        server.terminate()
        try:
            server.wait(30)
        except subprocess.TimeoutExpired:
            server.kill()

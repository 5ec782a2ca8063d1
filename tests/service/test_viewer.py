"""The web viewer page (``GET /v1/scenes/{id}/viewer``) against the render API, in a real browser.

A real server on 127.0.0.1 with the default model and the m3d_bedroom scene (references 00 + 02,
scene.json poses); Debian's chromium (software GL) driven by puppeteer-core (``viewer_browser.mjs``)
opens the viewer at frame 01's pose turned by several yaws and each screenshot is compared with the
API's perspective render of the same pose (default compositing = plain, over black): PSNR >= 35 dB.
Any console error, request leaving 127.0.0.1, failed request or a loaded splat count different from
the PLY's vertex count fails. With ``format=spz`` the page loads ``gaussians.spz`` (the same
Gaussians quantised, in SPZ's RUB world) and must match as well. ``scripts/test.sh`` installs
chromium and the npm packages; this test is never skipped. The same check runs on a scene POSTed
from 2048x1024 panoramas (zind_room09_2k, two yaws).

Also runnable as a script for the README figures:

    .venv/bin/python -m tests.service.test_viewer --json viewer.json [--page-shot docs/viewer.png]
"""

from __future__ import annotations

import argparse
import io
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image

from bench import DEV_DATA
from service.routes import viewer as viewer_route

from ._support import LiveServer, make_settings

ROOT = Path(__file__).resolve().parents[2]
DRIVER = Path(__file__).with_name("viewer_browser.mjs")
WIDTH, HEIGHT, FOV_DEG = 640, 480, 90.0
YAWS = (0, 90, 180, 270)
MIN_PSNR = 35.0


# -- helpers ---------------------------------------------------------------------------------------

def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR of two uint8 RGB images, on [0, 1]."""
    mse = float(np.mean((a.astype(np.float64) / 255 - b.astype(np.float64) / 255) ** 2))
    return math.inf if mse == 0 else 10 * math.log10(1.0 / mse)


def yawed(c2w: np.ndarray, yaw_deg: float) -> np.ndarray:
    """``c2w`` turned by ``yaw_deg`` about its own y axis (OpenCV: y down; +90 looks to the right)."""
    t = math.radians(yaw_deg)
    r = np.eye(4)
    r[:3, :3] = [[math.cos(t), 0, math.sin(t)], [0, 1, 0], [-math.sin(t), 0, math.cos(t)]]
    return c2w @ r


def ply_vertex_count(data: bytes) -> int:
    head = data[:4096].split(b"end_header", 1)[0].decode("ascii")
    return int(re.search(r"element vertex (\d+)", head).group(1))


def find_chromium() -> str:
    for name in ("chromium", "chromium-browser"):
        path = shutil.which(name)
        if path:
            return path
    return "/usr/bin/chromium"


def default_model(folder: Path) -> Path:
    from service.model_files import default_model_name, ensure_model

    return ensure_model(folder / default_model_name(), progress=lambda _msg: None)


@contextmanager
def scene_server(model: Path, store: Path, scene_dir: Path):
    """A live server holding the dev scene ``scene_dir`` (split 0 references); yields (server, scene id, scene.json)."""
    scene = json.loads((scene_dir / "scene.json").read_text())
    frames = {f["name"]: f for f in scene["frames"]}
    ref_a, ref_b = scene["splits"][0]["references"]
    poses = {"convention": scene["convention"], "c2w": [frames[ref_a]["c2w"], frames[ref_b]["c2w"]]}
    with LiveServer(make_settings(model, store)) as server, server.client() as client:
        files = {"image_a": (f"{ref_a}.png", (scene_dir / frames[ref_a]["image"]).read_bytes()),
                 "image_b": (f"{ref_b}.png", (scene_dir / frames[ref_b]["image"]).read_bytes())}
        r = client.post("/v1/scenes", files=files, data={"poses": json.dumps(poses)})
        assert r.status_code == 201, r.text
        yield server, r.json()["id"], scene


def target_pose(scene: dict) -> np.ndarray:
    frames = {f["name"]: f for f in scene["frames"]}
    return np.array(frames[scene["splits"][0]["targets"][0]]["c2w"], dtype=np.float64)


def measure(server_url: str, scene_id: str, c2w_base: np.ndarray, out_dir: Path, yaws=YAWS,
            page_shot: Path | None = None, page_shot_at_reference_a: bool = False, timeout_s: int = 240,
            file_format: str = "ply") -> dict:
    """Open the viewer (loading the scene's ``file_format`` file) at each yawed pose, screenshot, compare with
    the API render; return a report."""
    poses = [{"name": f"yaw{yaw}", "c2w": yawed(c2w_base, yaw).ravel().tolist()} for yaw in yaws]
    args = {"base_url": server_url, "scene_id": scene_id, "poses": poses, "width": WIDTH, "height": HEIGHT,
            "fov_deg": FOV_DEG, "out_dir": str(out_dir), "chromium": find_chromium(), "timeout_s": timeout_s,
            "format": file_format}
    if page_shot is not None:
        query = "" if page_shot_at_reference_a else "c2w=" + ",".join(repr(v) for v in c2w_base.ravel().tolist())
        args["page_shot"] = {"path": str(page_shot), "width": 720, "height": 450, "query": query}
    t0 = time.perf_counter()
    proc = subprocess.run(["node", str(DRIVER), json.dumps(args)], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout_s + 120)
    browser_s = time.perf_counter() - t0
    assert proc.returncode == 0, f"viewer driver failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}"
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    report["browser_seconds"] = browser_s
    with httpx.Client(base_url=server_url, timeout=300) as client:
        ply = client.get(f"/v1/scenes/{scene_id}/gaussians.ply")
        assert ply.status_code == 200
        report["ply_vertex_count"] = ply_vertex_count(ply.content)
        for view, pose in zip(report["views"], poses):
            r = client.get(f"/v1/scenes/{scene_id}/render", params={
                "c2w": ",".join(repr(v) for v in pose["c2w"]), "projection": "perspective",
                "width": WIDTH, "height": HEIGHT, "fov_deg": FOV_DEG})  # default compositing: plain
            assert r.status_code == 200, r.text
            api = np.asarray(Image.open(io.BytesIO(r.content)).convert("RGB"))
            (out_dir / f"api-{view['name']}.png").write_bytes(r.content)
            if view.get("screenshot") and Path(view["screenshot"]).is_file():
                shot = np.asarray(Image.open(view["screenshot"]).convert("RGB"))
                view["psnr_db"] = psnr(shot, api) if shot.shape == api.shape else None
                view["mean_api"], view["mean_viewer"] = float(api.mean() / 255), float(shot.mean() / 255)
    return report


# -- fixtures ----------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def m3d(tmp_path_factory, m3d_dir):
    model = default_model(tmp_path_factory.getbasetemp() / "omnisplat-default-model")
    with scene_server(model, tmp_path_factory.mktemp("viewer-store"), m3d_dir) as served:
        yield served


@pytest.fixture(scope="module")
def zind2k(tmp_path_factory, zind2k_dir):
    model = default_model(tmp_path_factory.getbasetemp() / "omnisplat-default-model")
    with scene_server(model, tmp_path_factory.mktemp("viewer-store-2k"), zind2k_dir) as served:
        yield served


# -- the browser test --------------------------------------------------------------------------------

def check_viewer_matches_api(served, out_dir: Path, yaws=YAWS, file_format: str = "ply") -> None:
    """The browser check of the module docstring on a served scene, at its first target's pose turned by ``yaws``,
    the page loading the scene's ``file_format`` file."""
    assert shutil.which("node"), "node is not installed: run `bash scripts/test.sh` (installs nodejs, npm)"
    assert Path(find_chromium()).exists(), "chromium is not installed: run `bash scripts/test.sh`"
    assert not viewer_route.missing_assets(), "viewer npm packages missing: run `npm ci` (scripts/test.sh does)"
    server, scene_id, scene = served
    t0 = time.perf_counter()
    report = measure(server.url, scene_id, target_pose(scene), out_dir, yaws=yaws, file_format=file_format)
    elapsed = time.perf_counter() - t0
    print(json.dumps({"seconds": elapsed, **report}, indent=1))
    assert report["console_errors"] == [], report["console_errors"]
    assert report["page_errors"] == [], report["page_errors"]
    assert report["external_requests"] == [], report["external_requests"]
    assert report["failed_requests"] == [], report["failed_requests"]
    assert len(report["views"]) == len(yaws)
    assert report["views"][0]["cross_origin_isolated"] is True  # COOP/COEP: SharedArrayBuffer sort
    assert report["views"][0]["download_percent"] == 100  # the panel showed the file's download to its end
    for view in report["views"]:
        assert view["error"] is None, view
        assert view["splat_count"] == report["ply_vertex_count"], view
        assert view["psnr_db"] is not None and view["psnr_db"] >= MIN_PSNR, view


def test_viewer_matches_api_render_in_chromium(m3d, tmp_path):
    check_viewer_matches_api(m3d, tmp_path)


def test_viewer_on_the_spz_matches_api_render_in_chromium(m3d, tmp_path):
    """``format=spz``: the quantised file in SPZ's RUB world, the page's camera turned into it."""
    check_viewer_matches_api(m3d, tmp_path, yaws=(0, 90), file_format="spz")


def test_viewer_matches_api_render_at_2048_input(zind2k, tmp_path):
    """A scene POSTed from 2048x1024 panoramas (zind_room09_2k): the same PLY contract at the larger input."""
    check_viewer_matches_api(zind2k, tmp_path, yaws=(0, 180))


def test_viewer_says_when_its_scene_file_cannot_be_loaded(m3d, tmp_path):
    """A scene deleted after its page was served (its PLY answers 404): the page says so in its panel, shown even
    with ``bare=1``, instead of waiting at 'downloading 0%' with the error uncaught."""
    server, scene_id, scene = m3d
    args = {"base_url": server.url, "scene_id": scene_id, "width": 320, "height": 240, "fov_deg": FOV_DEG,
            "poses": [{"name": "gone", "c2w": target_pose(scene).ravel().tolist()}], "out_dir": str(tmp_path),
            "chromium": find_chromium(), "timeout_s": 60, "scene_gone": True}
    proc = subprocess.run(["node", str(DRIVER), json.dumps(args)], cwd=ROOT, capture_output=True, text=True,
                          timeout=240)
    assert proc.returncode == 0, f"viewer driver failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}"
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    view = report["views"][0]
    assert view["error"] is not None and "Could not load file" in view["error"], view
    assert view["panel_visible"] is True, view
    assert report["page_errors"] == [], report["page_errors"]  # the failure is the page's, not uncaught


# -- the page without a browser ------------------------------------------------------------------------

def test_viewer_page_config_headers_and_assets(m3d):
    server, scene_id, scene = m3d
    with server.client() as client:
        r = client.get(f"/v1/scenes/{scene_id}/viewer")
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
        assert r.headers["cross-origin-opener-policy"] == "same-origin"
        assert r.headers["cross-origin-embedder-policy"] == "require-corp"
        page = r.text
        assert f'href="/v1/scenes/{scene_id}/gaussians.ply"' in page
        assert f'href="/v1/scenes/{scene_id}/gaussians.spz"' in page
        config = json.loads(re.search(r'id="omnisplat-config" type="application/json">(.*?)</script>', page,
                                      re.S).group(1))
        frames = {f["name"]: f for f in scene["frames"]}
        ref_a = frames[scene["splits"][0]["references"][0]]["c2w"]
        assert np.allclose(np.reshape(config["c2w"], (4, 4)), ref_a)  # starts at reference A
        assert config["ply"] == f"/v1/scenes/{scene_id}/gaussians.ply" and config["fov_deg"] == 90.0
        assert config["spz"] == f"/v1/scenes/{scene_id}/gaussians.spz"  # loaded with ?format=spz
        assert client.get(f"/v1/scenes/{scene_id}/viewer", params={"format": "spz"}).status_code == 200
        bad = client.get(f"/v1/scenes/{scene_id}/viewer", params={"format": "splat"})
        assert bad.status_code == 422 and "format" in bad.text
        # no CDN: every script/style/import comes from this server
        srcs = re.findall(r'(?:src|href)="([^"]+)"', page) + re.findall(r'"(/[^"]+\.js)"', page)
        assert srcs and all(s.startswith("/") or s.startswith("data:") for s in srcs), srcs
        for name in ("three.module.js", "three.core.js", "gaussian-splats-3d.module.js", "viewer.js"):
            a = client.get(f"/viewer-assets/{name}")
            assert a.status_code == 200 and a.headers["content-type"].startswith("text/javascript"), name
            assert a.headers["cross-origin-embedder-policy"] == "require-corp"
            assert "https://cdn" not in a.text
        for bad in ("package.json", "..%2Fpackage.json", "three.cjs"):
            assert client.get(f"/viewer-assets/{bad}").status_code == 404
        viewer_js = client.get("/viewer-assets/viewer.js").text
        assert "gpuAcceleratedSort: false" in viewer_js and "optimizeSplatData: false" in viewer_js
        assert "/v1/scenes/{scene_id}/viewer" in client.get("/openapi.json").json()["paths"]


def test_viewer_unknown_scene_is_404(m3d):
    server, _, _ = m3d
    with server.client() as client:
        r = client.get(f"/v1/scenes/{'0' * 32}/viewer")
        assert r.status_code == 404 and r.json()["error"]["code"] == "scene_not_found"
        assert client.get("/v1/scenes/not-an-id/viewer").status_code == 422


def test_viewer_without_npm_packages_is_503_and_api_unaffected(m3d, tmp_path, monkeypatch):
    server, scene_id, _ = m3d
    monkeypatch.setenv("OMNISPLAT_NODE_MODULES", str(tmp_path / "no-node-modules"))
    with server.client() as client:
        r = client.get(f"/v1/scenes/{scene_id}/viewer")
        assert r.status_code == 503
        err = r.json()["error"]
        assert err["code"] == "viewer_unavailable" and "npm ci" in err["message"] and "nodejs" in err["message"]
        assert client.get("/viewer-assets/three.module.js").status_code == 503
        assert client.get(f"/v1/scenes/{'0' * 32}/viewer").status_code == 404  # unknown scene first
        assert client.get("/healthz").status_code == 200
        assert client.get(f"/v1/scenes/{scene_id}").status_code == 200
        r = client.get(f"/v1/scenes/{scene_id}/render", params={"c2w": "1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1",
                                                                 "width": 64})
        assert r.status_code == 200


# -- script mode: the README figures ---------------------------------------------------------------------

def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="Viewer vs API PSNR on m3d_bedroom (the browser test, as figures)")
    p.add_argument("--json", type=Path, help="write the report here")
    p.add_argument("--model", type=Path, help="ONNX model (default: the default model, built if missing)")
    p.add_argument("--page-shot", type=Path, help="also screenshot the page (with its panel) at frame 01's pose "
                                                  "(a palette PNG)")
    p.add_argument("--page-shot-at-reference-a", action="store_true", help="... at the page's default pose instead")
    p.add_argument("--out", type=Path, help="keep the screenshots here")
    p.add_argument("--format", choices=("ply", "spz"), default="ply", help="the file the page loads")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        model = args.model or default_model(Path(os.environ.get("OMNISPLAT_MODELS_DIR", tmp / "models")))
        out = args.out or tmp / "shots"
        out.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        with scene_server(model, tmp / "store", DEV_DATA / "m3d_bedroom") as (server, scene_id, scene):
            report = measure(server.url, scene_id, target_pose(scene), out, page_shot=args.page_shot,
                             page_shot_at_reference_a=args.page_shot_at_reference_a, file_format=args.format)
        if args.page_shot:  # small enough to commit
            Image.open(args.page_shot).convert("RGB").quantize(256).save(args.page_shot, optimize=True)
        report["total_seconds"] = time.perf_counter() - t0
        report["model"] = model.name
    rows = [f"| {v['name']} | {v.get('psnr_db', float('nan')):.2f} | {v['splat_count']} |" for v in report["views"]]
    print("| pose (frame 01, yaw) | viewer vs API PSNR (dB) | splats loaded |\n|---|---|---|\n" + "\n".join(rows))
    print(f"PLY vertices {report['ply_vertex_count']}; browser {report['browser_seconds']:.1f} s; "
          f"total {report['total_seconds']:.1f} s; console errors {len(report['console_errors'])}; "
          f"external requests {len(report['external_requests'])}")
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

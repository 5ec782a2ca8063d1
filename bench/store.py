"""Scene store and server memory: disk per scene, the store budget under an edit flood, RSS after a POST/render run.

Three measurements against a real server (``uvicorn`` in a subprocess, the real model, a dev scene's panoramas
at their own size):

* ``disk``: bytes per file of one stored scene, next to what the same scene took with float32 arrays and a PLY
  copy written on first download (the arrays re-encoded with ``np.savez`` in float32, exactly that format);
  the PLY's size and download seconds (streamed from the stored arrays).
* ``budget``: a store budget of ``--budget-scenes`` scenes; one selection, then ``--edits`` recolours of
  the scene (each a new 50 MB-class scene): the statuses, how many scenes were evicted, and the store's
  bytes after every edit against the budget (it must never pass it).
* ``rss``: RSS of the server at start, after ``--posts`` reconstructions (distinct scene ids) and after
  ``--renders`` ERP renders, plus the peak (VmHWM); once with :func:`service.memory.release_memory` and once
  without (``--compare``), each in a fresh server.

``omnisplat-bench store [--posts 30 --renders 200]`` prints JSON (and writes ``--json``).
"""

from __future__ import annotations

import argparse
import io
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

from bench import DEV_DATA
from bench.service import free_port, wait_ready

ROOT = Path(__file__).resolve().parents[1]

#: The server as the settings describe it, budget included (the store is built from the settings),
#: optionally without releasing memory after requests.
_LAUNCH = r"""
import sys, uvicorn
import service.app as app_module
from service import memory
from service.config import Settings
from service.server import server_config
from service.store import SceneStore

settings = Settings()
memory.enabled = sys.argv[1] == "1"

class _Store(SceneStore):
    def __init__(self, root, **kw):
        super().__init__(root, **{**kw, "budget_bytes": settings.store_budget_bytes,
                                  "min_free_bytes": settings.min_free_store_bytes})

app_module.SceneStore = _Store
uvicorn.Server(server_config(app_module.create_app(settings), settings, log_level="critical")).run()
"""


class Server:
    def __init__(self, model: Path, store: Path, trim: bool = True, **env) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.env = {k: v for k, v in os.environ.items() if not k.startswith("OMNISPLAT_")}
        self.env.update({"OMNISPLAT_MODEL_PATH": str(model), "OMNISPLAT_STORE_DIR": str(store),
                         "OMNISPLAT_PORT": str(self.port), "PYTHONPATH": str(ROOT),
                         **{f"OMNISPLAT_{k.upper()}": str(v) for k, v in env.items()}})
        self.trim = trim

    def __enter__(self) -> "Server":
        self.proc = subprocess.Popen([sys.executable, "-c", _LAUNCH, "1" if self.trim else "0"], cwd=ROOT, env=self.env)
        wait_ready(self.url, self.proc, 300, poll_s=0.2)
        return self

    def __exit__(self, *exc) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(30)
        except subprocess.TimeoutExpired:
            self.proc.kill()

    def memory_mb(self) -> dict[str, float]:
        out = {}
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith(("VmRSS:", "VmHWM:")):
                out[line.split(":")[0]] = round(int(line.split()[1]) / 1024, 1)
        return {"rss_mb": out.get("VmRSS"), "peak_mb": out.get("VmHWM")}


def _inputs(scene_dir: Path) -> list[tuple[bytes, list]]:
    """(PNG bytes, c2w) of every frame of a dev scene, at its own size."""
    from PIL import Image

    meta = json.loads((scene_dir / "scene.json").read_text())
    out = []
    for frame in meta["frames"]:
        buf = io.BytesIO()
        Image.open(scene_dir / frame["image"]).convert("RGB").save(buf, format="PNG")
        out.append((buf.getvalue(), frame["c2w"]))
    return out


def _post(c: httpx.Client, frames, i: int, j: int, k: int = 0) -> httpx.Response:
    (a, ca), (b, cb) = frames[i], frames[j]
    data = {"poses": json.dumps({"convention": "opencv", "c2w": [ca, cb]}),
            "options": json.dumps({"far": 20.0 + 0.01 * k})}  # a distinct scene id per k: a real reconstruction
    return c.post("/v1/scenes", files={"image_a": ("a.png", a), "image_b": ("b.png", b)}, data=data)


def _folder_bytes(folder: Path) -> dict[str, int]:
    return {p.name: p.stat().st_size for p in sorted(folder.iterdir()) if p.is_file()}


def disk(model: Path, tmp: Path, frames) -> dict:
    from service.store import SceneStore

    store_dir = tmp / "store-disk"
    with Server(model, store_dir) as srv, httpx.Client(base_url=srv.url, timeout=600) as c:
        r = _post(c, frames, 0, 1)
        r.raise_for_status()
        sid = r.json()["id"]
        folder = store_dir / "scenes" / sid
        files = _folder_bytes(folder)
        t0 = time.perf_counter()
        ply = c.get(f"/v1/scenes/{sid}/gaussians.ply")
        ply_s = time.perf_counter() - t0
        after_download = _folder_bytes(folder)
    g = SceneStore(store_dir).gaussians(sid)
    buf = io.BytesIO()
    np.savez(buf, **{f: getattr(g, f).astype(np.float32) for f in ("means", "scales", "quats", "opacities", "sh")})
    float32_npz = len(buf.getvalue())
    now = sum(after_download.values())
    before = now - files["gaussians.npz"] + float32_npz + len(ply.content)
    return {"num_gaussians": len(g), "files": files, "ply_bytes": len(ply.content), "ply_download_s": round(ply_s, 2),
            "files_after_ply_download": after_download, "bytes_per_scene_after_download": now,
            "float32_npz_bytes": float32_npz,
            "bytes_per_scene_float32_with_ply_copy": before,
            "bytes_per_gaussian_npz": round(files["gaussians.npz"] / len(g), 1),
            "bytes_per_gaussian_npz_float32": round(float32_npz / len(g), 1)}


def budget(model: Path, tmp: Path, frames, scenes: float, edits: int, scene_bytes: int) -> dict:
    from service.store import SceneStore

    store_dir = tmp / "store-budget"
    limit = int(scenes * scene_bytes)
    statuses, over, usage = [], 0, []
    with Server(model, store_dir, store_budget_bytes=limit) as srv, httpx.Client(base_url=srv.url, timeout=600) as c:
        sid = _post(c, frames, 0, 1).json()["id"]
        sel = c.post(f"/v1/scenes/{sid}/selections", json={"view": "a", "points": [[0.5, 0.5]]})
        sel.raise_for_status()
        t0 = time.perf_counter()
        for k in range(edits):
            r = c.post(f"/v1/scenes/{sid}/edits", json={"selection": sel.json()["id"], "op": "recolor",
                                                        "color": [k / max(edits, 1), 0.3, 0.7]})
            statuses.append(r.status_code)
            used = SceneStore(store_dir, budget_bytes=0).usage()
            usage.append(used)
            over += used > limit
        seconds = time.perf_counter() - t0
        metrics = {line.split()[0]: float(line.split()[1]) for line in c.get("/metrics").text.splitlines()
                   if line.startswith("omnisplat_store")}
    return {"budget_bytes": limit, "edits": edits, "statuses": {str(s): statuses.count(s) for s in sorted(set(statuses))},
            "max_store_bytes": max(usage), "times_over_budget": over, "edits_per_s": round(edits / seconds, 2),
            "metrics": metrics, "scenes_left": len(SceneStore(store_dir, budget_bytes=0).ids())}


def rss(model: Path, tmp: Path, frames, posts: int, renders: int, width: int, trim: bool) -> dict:
    store_dir = tmp / f"store-rss-{int(trim)}"
    out: dict = {"trim": trim, "posts": posts, "renders": renders, "render_width": width}
    pairs = [(i, j) for i in range(len(frames)) for j in range(len(frames)) if i != j]
    rng = np.random.default_rng(0)
    with Server(model, store_dir, trim=trim) as srv, httpx.Client(base_url=srv.url, timeout=600) as c:
        out["start"] = srv.memory_mb()
        ids, t0 = [], time.perf_counter()
        for k in range(posts):
            i, j = pairs[k % len(pairs)]
            r = _post(c, frames, i, j, k)
            r.raise_for_status()
            ids.append(r.json()["id"])
        out["post_s"] = round(time.perf_counter() - t0, 1)
        out["after_posts"] = srv.memory_mb()
        t0 = time.perf_counter()
        for k in range(renders):
            pose = np.eye(4)
            pose[:3, 3] = rng.uniform(-0.3, 0.3, 3)
            c2w = ",".join(f"{v:.6g}" for v in pose.ravel())
            r = c.get(f"/v1/scenes/{ids[k % len(ids)]}/render", params={"c2w": c2w, "width": width})
            r.raise_for_status()
        out["render_s"] = round(time.perf_counter() - t0, 1)
        out["after_renders"] = srv.memory_mb()
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="omnisplat-bench store", description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, default=DEV_DATA / "zind_room09", help="dev scene folder (scene.json)")
    p.add_argument("--model", type=Path, help="ONNX model (default: the service's default model file)")
    p.add_argument("--posts", type=int, default=30)
    p.add_argument("--renders", type=int, default=200)
    p.add_argument("--render-width", type=int, default=1024)
    p.add_argument("--edits", type=int, default=20)
    p.add_argument("--budget-scenes", type=float, default=4.0, help="store budget in scenes of the measured size")
    p.add_argument("--compare", action="store_true", help="also run the RSS sequence without release_memory")
    p.add_argument("--skip", nargs="*", default=[], choices=["disk", "budget", "rss"])
    p.add_argument("--json", type=Path, help="write the results here too")
    args = p.parse_args(argv)

    from service.config import Settings

    model = args.model or Settings().resolved_model_path
    frames = _inputs(args.data)
    res: dict = {"data": args.data.name, "model": model.name, "load": os.getloadavg()}
    with tempfile.TemporaryDirectory(prefix="omnisplat-store-bench-") as tmp:
        tmp = Path(tmp)
        if "disk" not in args.skip:
            res["disk"] = disk(model, tmp, frames)
        if "budget" not in args.skip:
            scene_bytes = res.get("disk", {}).get("bytes_per_scene_after_download", 40 << 20)
            res["budget"] = budget(model, tmp, frames, args.budget_scenes, args.edits, scene_bytes)
        if "rss" not in args.skip:
            res["rss"] = [rss(model, tmp, frames, args.posts, args.renders, args.render_width, True)]
            if args.compare:
                res["rss"].append(rss(model, tmp, frames, args.posts, args.renders, args.render_width, False))
    text = json.dumps(res, indent=1)
    print(text)
    if args.json:
        args.json.write_text(text + "\n")
    return 1 if res.get("budget", {}).get("times_over_budget") else 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Rerun the reliability audit against a real server on 127.0.0.1 and summarise it.

    omnisplat-bench reliability [--model M.onnx] [--json out.json]

Categories (bounded in count and time): bad inputs by kind (status codes), protocol abuse
(oversized headers, Content-Length with Transfer-Encoding, HEAD), schemathesis on every
operation, overload (503 + Retry-After), idle and trickling connections (health must stay
200, the connections must be closed), slow request bodies against the upload slots (renders,
info and metadata must keep answering 200 while ``--slow-bodies`` clients trickle one byte
every 3 s), PNG chunk bombs posted at once (status, seconds, server RSS), kill -9 during
writes then restart (no lost or corrupt scene), and a full then read-only store on a small
tmpfs (needs root; 507 and /readyz 503, mounts removed afterwards). ``--sections`` runs a
subset. Every client talks to 127.0.0.1 only. Without ``--model`` a small model (128x256,
8 planes) is exported first (needs torch). Prints JSON and a markdown table; exit status 1
when any answer was a 5xx other than 503/507, a scene was lost or corrupt, health failed, or
a render/info/metadata request was not answered 200 under the slow bodies.
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np

from bench.reliability_http import chunk_bombs, multipart, png_rows, protocol, slow_bodies
from bench.service import free_port, post_inputs, wait_ready

ROOT = Path(__file__).resolve().parents[1]
HUGE = "1" + "0" * 399


class Server:
    """``omnisplat serve`` in a subprocess on a free loopback port."""

    def __init__(self, model: Path, store: Path, store_ok: bool = True, **env) -> None:
        self.model, self.store, self.env, self.store_ok = model, store, env, store_ok
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.proc: subprocess.Popen | None = None

    def start(self) -> "Server":
        env = {k: v for k, v in os.environ.items() if not k.startswith("OMNISPLAT_")}
        env.update({f"OMNISPLAT_{k.upper()}": str(v) for k, v in self.env.items()})
        self.proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--no-build", "--model",
                                      str(self.model), "--store", str(self.store), "--port", str(self.port),
                                      "--log-level", "critical"], cwd=ROOT, env=env)
        # ready, or (expected) the model is loaded and only the store is refused
        wait_ready(self.url, self.proc, 180, accept=lambda r: not self.store_ok and "store" in str(r.json().get("error")))
        return self

    def kill9(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(30)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()

    def __enter__(self) -> "Server":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def _post(c: httpx.Client, a: bytes, b: bytes, poses: str, options: str | None = None) -> httpx.Response:
    data = {"poses": poses, **({"options": options} if options is not None else {})}
    return c.post("/v1/scenes", files={"image_a": ("a.png", a), "image_b": ("b.png", b)}, data=data)


def _poses(ca, cb) -> str:
    return json.dumps({"convention": "opencv", "c2w": [ca, cb]})


def _far(i: int) -> str:
    return json.dumps({"far": 20.0 + 0.01 * i})  # a distinct scene id per i: a real reconstruction


def bad_inputs(srv: Server, imgs) -> dict:
    """One request per kind of bad input; the status each got."""
    import io

    from PIL import Image

    a, b, ca, cb = imgs
    poses = _poses(ca, cb)
    grey16 = []  # the pair as 16-bit grey PNGs: a format that decodes to other than 8-bit RGB
    for data in (a, b):
        buf = io.BytesIO()
        luma = np.asarray(Image.open(io.BytesIO(data)).convert("L"), np.uint16) * 257
        Image.fromarray(luma).save(buf, format="PNG")
        grey16.append(buf.getvalue())
    far = np.eye(4)
    far[0, 3] = 1e7
    moved = far.copy()
    moved[0, 3] += 0.5
    out = {}
    with httpx.Client(base_url=srv.url, timeout=120) as c:
        sid = _post(c, a, b, poses).json()["id"]
        eye = ",".join(str(v) for v in np.eye(4).ravel())
        parts = [("image_a", a), ("image_b", b), ("poses", poses.encode())]
        body_open, mp_headers = multipart(parts, close=False)
        body_twice, _ = multipart([*parts, ("poses", poses.encode())])
        cases = {
            "huge_int_near": lambda: _post(c, a, b, poses, f'{{"near": {HUGE}}}'),
            "huge_int_margin": lambda: _post(c, a, b, poses, f'{{"adaptive_range": {{"margin": {HUGE}}}}}'),
            "huge_int_pose": lambda: _post(c, a, b, poses.replace("0.5", HUGE, 1) if "0.5" in poses else
                                           poses.replace("1.0", HUGE, 1)),
            "near_far_extreme": lambda: _post(c, a, b, poses, '{"near": 1e-300, "far": 1e300}'),
            "cameras_1e7_from_origin": lambda: _post(c, a, b, _poses(far.tolist(), moved.tolist())),
            "baseline_1e20": lambda: _post(c, a, b, _poses(np.eye(4).tolist(),
                                                           [[1, 0, 0, 1e20], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])),
            "baseline_2um": lambda: _post(c, a, b, _poses(np.eye(4).tolist(),
                                                          [[1, 0, 0, 2e-6], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])),
            "grey16_png": lambda: _post(c, grey16[0], grey16[1], poses),
            "not_an_image": lambda: _post(c, b"hello", b, poses),
            "render_perspective_4096x2048": lambda: c.get(f"/v1/scenes/{sid}/render", params={
                "c2w": eye, "projection": "perspective", "width": 4096, "height": 2048}),
            "render_perspective_2048_fov170": lambda: c.get(f"/v1/scenes/{sid}/render", params={
                "c2w": eye, "projection": "perspective", "width": 2048, "height": 2048, "fov_deg": 170}),
            "render_yin_4095": lambda: c.get(f"/v1/scenes/{sid}/render", params={
                "c2w": eye, "projection": "yin", "width": 4095}),
            "refine_malformed_json": lambda: c.post(f"/v1/scenes/{sid}/refine", content=b'{"iterations": ',
                                                    headers={"content-type": "application/json"}),
            "method_put_scene": lambda: c.put(f"/v1/scenes/{sid}"),
            "foreign_origin_post": lambda: c.post("/v1/scenes", headers={"Origin": "http://evil.example"}),
            "rebinding_host": lambda: c.get("/v1/info", headers={"Host": "evil.example"}),
            "png_8192x4096_3_rows": lambda: _post(c, a, png_rows(8192, 4096, 3), poses),
            "multipart_no_closing_boundary": lambda: c.post("/v1/scenes", content=body_open, headers=mp_headers),
            "multipart_poses_twice": lambda: c.post("/v1/scenes", content=body_twice, headers=mp_headers),
            "viewer_key_twice": lambda: c.get(f"/v1/scenes/{sid}/viewer", params=[("key", "a"), ("key", "b")]),
        }
        for name, call in cases.items():
            r = call()
            is_json = r.headers.get("content-type", "").startswith("application/json")
            out[name] = {"status": r.status_code, "json": is_json,
                         "message": (r.json().get("error") or {}).get("message", "")[:160] if is_json else r.text[:80]}
        out["_after"] = {"status": c.get("/healthz").status_code, "json": True, "message": "keep-alive still usable"}
    return out


def fuzz(srv: Server, imgs, max_examples: int, budget_s: float) -> dict:
    """schemathesis over every operation, ``max_examples`` each, within ``budget_s``."""
    import collections

    import requests
    import schemathesis
    from hypothesis import HealthCheck, given, settings

    a, b, ca, cb = imgs
    schema = schemathesis.openapi.from_url(srv.url + "/openapi.json")
    seen: collections.Counter = collections.Counter()
    failures: list[str] = []
    start = time.monotonic()
    with requests.Session() as session:
        for op in [r.ok() for r in schema.get_all_operations()]:
            @settings(max_examples=max_examples, deadline=None, database=None, derandomize=True,
                      suppress_health_check=list(HealthCheck))
            @given(case=op.as_strategy())
            def check(case):
                if time.monotonic() - start > budget_s:
                    return
                if case.path == "/v1/scenes" and isinstance(case.body, dict) and seen.total() % 2:
                    case.body.update(image_a=a, image_b=b, poses=_poses(ca, cb))
                r = case.call(base_url=srv.url, session=session, timeout=120)
                seen[r.status_code] += 1
                if r.status_code >= 500 and r.status_code != 503:
                    failures.append(f"{case.method.upper()} {case.formatted_path} -> {r.status_code}")

            check()
    return {"cases": seen.total(), "statuses": dict(sorted(seen.items())), "server_errors": failures[:10]}


def overload(srv: Server, imgs, n: int) -> dict:
    """``n`` simultaneous reconstructions against a queue of 1: 201s and JSON 503 + Retry-After."""
    a, b, ca, cb = imgs

    def one(i):
        with httpx.Client(base_url=srv.url, timeout=300) as c:
            try:
                return _post(c, a, b, _poses(ca, cb), _far(1000 + i))
            except httpx.TransportError as exc:
                return exc

    with ThreadPoolExecutor(n) as pool:
        rs = list(pool.map(one, range(n)))
    answers = [r for r in rs if isinstance(r, httpx.Response)]
    busy = [r for r in answers if r.status_code == 503]
    return {"requests": n, "statuses": sorted(r.status_code for r in answers),
            "dropped": len(rs) - len(answers),
            "busy_with_retry_after_json": sum("retry-after" in r.headers and r.json()["error"]["code"] == "busy"
                                              for r in busy), "busy": len(busy)}


def idle_connections(srv: Server, n_idle: int, n_slow: int, header_timeout: float) -> dict:
    """``n_idle`` silent and ``n_slow`` trickling connections; health polled meanwhile; closed after?"""
    host, port = "127.0.0.1", srv.port
    idle = [socket.create_connection((host, port), timeout=10) for _ in range(n_idle)]
    slow = [socket.create_connection((host, port), timeout=10) for _ in range(n_slow)]
    stop = threading.Event()

    def trickle():
        for s in slow:
            s.sendall(b"POST /v1/scenes HTTP/1.1\r\n")
        while not stop.is_set():
            for s in slow:
                try:
                    s.sendall(b"X")
                except OSError:
                    pass
            time.sleep(1.0)

    t = threading.Thread(target=trickle, daemon=True)
    t.start()
    health = []
    with httpx.Client(base_url=srv.url, timeout=10) as c:
        for _ in range(10):
            try:
                r = c.get("/healthz")
                health.append(r.status_code)
            except httpx.TransportError:
                health.append(0)
            time.sleep(header_timeout / 5)
    time.sleep(header_timeout + 1.0)
    stop.set()
    t.join(5)

    def closed(s):
        s.settimeout(0.5)
        try:
            return s.recv(1) == b""
        except socket.timeout:
            return False
        except OSError:
            return True

    result = {"idle": n_idle, "trickling": n_slow, "health_statuses": sorted(set(health)),
              "health_non_200": sum(h != 200 for h in health),
              "closed_by_server": sum(closed(s) for s in idle + slow)}
    for s in idle + slow:
        s.close()
    return result


def _verify_store(srv: Server, acknowledged: set[str]) -> dict:
    """Every acknowledged scene present; every stored scene readable (meta, render, PLY)."""
    import io

    from plyfile import PlyData

    scenes = sorted(p.name for p in (srv.store / "scenes").iterdir() if (p / "meta.json").is_file())
    eye = ",".join(str(v) for v in np.eye(4).ravel())
    corrupt = []
    with httpx.Client(base_url=srv.url, timeout=120) as c:
        for sid in scenes:
            meta = c.get(f"/v1/scenes/{sid}")
            render = c.get(f"/v1/scenes/{sid}/render", params={"c2w": eye, "width": 64})
            ply = c.get(f"/v1/scenes/{sid}/gaussians.ply")
            ok = meta.status_code == render.status_code == ply.status_code == 200
            if ok:
                ok = PlyData.read(io.BytesIO(ply.content))["vertex"].count == meta.json()["num_gaussians"]
            if not ok:
                corrupt.append(sid)
    return {"stored": len(scenes), "lost": sorted(acknowledged - set(scenes)), "corrupt": corrupt,
            "leftover_tmp": len(list((srv.store / "tmp").iterdir()))}


def kill_during_writes(model: Path, store: Path, imgs, rounds: int) -> dict:
    """Four clients posting new scenes back to back, kill -9 mid-stream, restart; then verify the store.

    The kill comes 2 to 6 times one POST's duration (measured first, on the same server) after the
    clients start, so that with any model some scenes are acknowledged and others are cut off mid-write."""
    a, b, ca, cb = imgs
    rng = np.random.default_rng(0)
    acknowledged: set[str] = set()
    per_round = []
    counter = iter(range(10**6))
    srv = Server(model, store, inference_queue=8)
    srv.start()
    try:
        with httpx.Client(base_url=srv.url, timeout=300) as c:
            t0 = time.monotonic()
            first = _post(c, a, b, _poses(ca, cb), _far(next(counter)))
            post_s = time.monotonic() - t0
    finally:
        srv.stop()
    if first.status_code != 201:
        raise RuntimeError(f"the kill check's first scene was not stored: {first.text[:300]}")
    acknowledged.add(first.json()["id"])
    for _ in range(rounds):
        srv.start()
        statuses: list = []

        def client():
            with httpx.Client(base_url=srv.url, timeout=300) as c:
                while True:
                    try:
                        r = _post(c, a, b, _poses(ca, cb), _far(next(counter)))
                    except httpx.TransportError:
                        statuses.append(None)  # the server died under this request
                        return
                    statuses.append(r.status_code)
                    if r.status_code == 201:
                        acknowledged.add(r.json()["id"])

        with ThreadPoolExecutor(4) as pool:
            for _ in range(4):
                pool.submit(client)
            time.sleep(float(rng.uniform(2.0, 6.0)) * post_s)
            srv.kill9()
        per_round.append({"answered": sorted(set(s for s in statuses if s is not None)),
                          "created": statuses.count(201), "cut_off": statuses.count(None)})
    srv.start()
    try:
        check = _verify_store(srv, acknowledged)
    finally:
        srv.stop()
    return {"post_seconds": round(post_s, 2), "rounds": per_round, "acknowledged": len(acknowledged), **check}


def full_and_read_only_store(model: Path, imgs, scenes: float = 2.5) -> dict:
    """A tmpfs store with room for about ``scenes`` of the model's scenes filled up, then remounted read-only
    (root only; unmounted after). The tmpfs is sized after the first scene is written (a remount), so the
    check fills the disk whatever the model's scene size."""
    a, b, ca, cb = imgs
    mnt = Path(tempfile.mkdtemp(prefix="omnisplat-tmpfs-"))
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1g", "tmpfs", str(mnt)],
                             capture_output=True, text=True)
    if mounted.returncode != 0:
        mnt.rmdir()
        return {"skipped": f"cannot mount a tmpfs: {mounted.stderr.strip()[:120]}"}
    out: dict = {}
    try:
        # a tiny free-space margin first, so that the disk really fills up under a write
        with Server(model, mnt, min_free_store_bytes=64 * 1024) as srv, \
                httpx.Client(base_url=srv.url, timeout=120) as c:
            first = _post(c, a, b, _poses(ca, cb), _far(1999))
            if first.status_code != 201:
                raise RuntimeError(f"the first scene of the store-full check was not stored: {first.text[:300]}")
            scene_bytes = sum(f.stat().st_size for f in (mnt / "scenes" / first.json()["id"]).iterdir())
            size_mb = math.ceil(shutil.disk_usage(mnt).used / 2**20 + scenes * scene_bytes / 2**20)
            subprocess.run(["mount", "-o", f"remount,size={size_mb}m", str(mnt)], check=True)
            out.update(tmpfs_mb=size_mb, scene_mb=round(scene_bytes / 2**20, 1))
            statuses = [first.status_code]
            for i in range(40):  # until the disk is full
                r = _post(c, a, b, _poses(ca, cb), _far(2000 + i))
                statuses.append(r.status_code)
                if r.status_code == 507:
                    break
            out["full"] = {"statuses": sorted(set(statuses)), "posts": len(statuses),
                           "code": r.json()["error"]["code"] if r.status_code >= 400 else None,
                           "readyz": c.get("/readyz").status_code}
        # a margin beyond what the full disk has left (the default's role on a real disk): refused before any
        # work, and not ready
        margin = shutil.disk_usage(mnt).free + 2**20
        out["free_mb_when_full"] = round((margin - 2**20) / 2**20, 1)
        with Server(model, mnt, store_ok=False, min_free_store_bytes=margin) as srv, \
                httpx.Client(base_url=srv.url, timeout=120) as c:
            r = _post(c, a, b, _poses(ca, cb), _far(2500))
            out["free_space_precheck"] = {"post": r.status_code, "seconds": round(r.elapsed.total_seconds(), 3),
                                          "readyz": c.get("/readyz").status_code}
            sid = next(p.name for p in (mnt / "scenes").iterdir())
            subprocess.run(["mount", "-o", "remount,ro", str(mnt)], check=True)
            out["read_only"] = {
                "post": _post(c, a, b, _poses(ca, cb), _far(3000)).status_code,
                "delete": c.delete(f"/v1/scenes/{sid}").status_code,
                "ply_first_download": c.get(f"/v1/scenes/{sid}/gaussians.ply").status_code,
                "readyz": c.get("/readyz").status_code,
                "scene_still_there": c.get(f"/v1/scenes/{sid}").status_code,
            }
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)
        mnt.rmdir()
    return out


def _server_errors(obj) -> int:
    """5xx other than 503/507 anywhere in the collected statuses."""
    if isinstance(obj, dict):
        return sum(_server_errors(v) for k, v in obj.items() if k != "server_errors") + \
            len(obj.get("server_errors", []))
    if isinstance(obj, list):
        return sum(_server_errors(v) for v in obj)
    return int(isinstance(obj, int) and 500 <= obj < 600 and obj not in (503, 507))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="omnisplat-bench reliability", description=__doc__.splitlines()[0])
    p.add_argument("--model", type=Path, help="ONNX model (default: export a small one, needs torch)")
    p.add_argument("--fuzz-examples", type=int, default=15, help="schemathesis cases per operation")
    p.add_argument("--fuzz-seconds", type=float, default=90.0)
    p.add_argument("--kill-rounds", type=int, default=3)
    p.add_argument("--idle", type=int, default=100, help="idle connections held open")
    p.add_argument("--slow-bodies", type=int, default=300, help="clients trickling a request body at once")
    p.add_argument("--slow-seconds", type=float, default=20.0, help="how long the slow-body clients stay")
    p.add_argument("--bomb-chunks", type=int, default=7_000_000, help="empty private chunks per PNG chunk bomb")
    p.add_argument("--sections", default=",".join(SECTIONS), help=f"comma-separated subset of {', '.join(SECTIONS)}")
    p.add_argument("--json", type=Path, help="write the summary here too")
    args = p.parse_args(argv)
    sections = set(args.sections.split(","))
    if sections - set(SECTIONS):
        p.error(f"unknown sections {sorted(sections - set(SECTIONS))}")

    t_start = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="omnisplat-reliability-") as tmp:
        tmp = Path(tmp)
        model = args.model
        if model is None:
            from export.onnx_export import export_model

            model = Path(export_model(tmp / "small.onnx", height=128, width=256, num_planes=8))
        imgs = post_inputs(128)
        res: dict = {}
        header_timeout = 2.0
        with Server(model, tmp / "store", header_timeout_s=header_timeout, body_timeout_s=10,
                    inference_queue=1, max_render_width=4096, max_render_pixels=4096 * 2048) as srv:
            if "bad_inputs" in sections:
                res["bad_inputs"] = bad_inputs(srv, imgs)
            if "protocol" in sections:
                res["protocol"] = protocol(srv)
            if "schemathesis" in sections:
                res["schemathesis"] = fuzz(srv, imgs, args.fuzz_examples, args.fuzz_seconds)
            if "overload" in sections:
                res["overload"] = overload(srv, imgs, 8)
            if "idle_connections" in sections:
                res["idle_connections"] = idle_connections(srv, args.idle, 5, header_timeout)
            if "chunk_bombs" in sections:
                a, b, ca, cb = imgs
                res["chunk_bombs"] = chunk_bombs(srv, lambda c, x, y: _post(c, x, y, _poses(ca, cb)), a, b, 3,
                                                 args.bomb_chunks)
        if "slow_bodies" in sections:  # the default slots and body rate (64 uploads, 1 kB/s over 10 s)
            with Server(model, tmp / "store-slow") as srv, httpx.Client(base_url=srv.url, timeout=120) as c:
                a, b, ca, cb = imgs
                sid = _post(c, a, b, _poses(ca, cb)).json()["id"]
                res["slow_bodies"] = slow_bodies(srv, sid, args.slow_bodies, args.slow_seconds)
        if "kill_9_during_writes" in sections:
            res["kill_9_during_writes"] = kill_during_writes(model, tmp / "store-kill", imgs, args.kill_rounds)
        if "store_full_and_read_only" in sections:
            res["store_full_and_read_only"] = full_and_read_only_store(model, imgs)
    kill = res.get("kill_9_during_writes", {"lost": [], "corrupt": []})
    summary = {"sections": sorted(sections), "server_errors_5xx": _server_errors(res), "lost_scenes": len(kill["lost"]),
               "corrupt_scenes": len(kill["corrupt"]),
               "health_non_200_under_idle_load": res.get("idle_connections", {}).get("health_non_200", 0),
               "render_info_meta_not_200_under_slow_bodies": res.get("slow_bodies", {}).get("render_info_meta_not_200",
                                                                                            0),
               "seconds": round(time.monotonic() - t_start, 1)}
    res["summary"] = summary
    text = json.dumps(res, indent=1, default=str)
    print(text)
    print("\n| check | result |\n|---|---|")
    for k, v in summary.items():
        print(f"| {k} | {v} |")
    for name, case in res.get("bad_inputs", {}).items():
        print(f"| bad input `{name}` | {case['status']} |")
    if args.json:
        args.json.write_text(text + "\n")
    bad = summary["server_errors_5xx"] or summary["lost_scenes"] or summary["corrupt_scenes"] \
        or summary["health_non_200_under_idle_load"] or summary["render_info_meta_not_200_under_slow_bodies"]
    return 1 if bad else 0


SECTIONS = ("bad_inputs", "protocol", "schemathesis", "overload", "idle_connections", "chunk_bombs", "slow_bodies",
            "kill_9_during_writes", "store_full_and_read_only")


if __name__ == "__main__":
    raise SystemExit(main())

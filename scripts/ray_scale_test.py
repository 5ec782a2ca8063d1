"""Driver of scripts/ray-scale-test.sh: checks and throughput through a Ray Serve proxy on 127.0.0.1.

    ray_scale_test.py URL STORE_DIR PHASE [--seconds S] [--clients N] [--replicas R]

PHASE ``wait``: until R distinct replicas answer ``/readyz`` 200 (20 reads in a row all 200).
PHASE ``bench``: scenes POSTed and renders per minute over S seconds each, N clients.
PHASE ``checks`` (2 replicas): a scene POSTed, rendered and refined through the proxy; job status
read until two replicas have answered (``X-Omnisplat-Replica``); the replica running a long
refinement killed with SIGKILL: requests keep being answered, the job is reported failed
(``replica_lost``), a new attempt succeeds, and every stored scene reads back whole.
Prints one JSON line per phase; exit status 1 when a check fails. Standard library + numpy/Pillow.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import signal
import sys
import threading
import time
import urllib.error
import urllib.request
import uuid
from pathlib import Path

import numpy as np
from PIL import Image

# the dev scene beside the checkout (../shared/data), unless OMNISPLAT_SCALE_DATA names another scene folder
DATA = Path(os.environ.get("OMNISPLAT_SCALE_DATA", Path(__file__).resolve().parents[2] / "shared" / "data" / "m3d_bedroom"))
HEADER = "x-omnisplat-replica"


def request(url: str, method: str = "GET", body: bytes | None = None, headers: dict | None = None,
            timeout: float = 120.0) -> tuple[int, dict, bytes]:
    req = urllib.request.Request(url, data=body, method=method, headers=headers or {})
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            return r.status, {k.lower(): v for k, v in r.headers.items()}, r.read()
    except urllib.error.HTTPError as e:
        return e.code, {k.lower(): v for k, v in e.headers.items()}, e.read()
    except OSError as e:  # refused / reset / timed out: no HTTP answer at all
        return 0, {}, str(e).encode()


def multipart(fields: dict[str, str], files: dict[str, tuple[str, bytes]]) -> tuple[bytes, str]:
    boundary = uuid.uuid4().hex
    out = io.BytesIO()
    for name, value in fields.items():
        out.write(f'--{boundary}\r\nContent-Disposition: form-data; name="{name}"\r\n\r\n{value}\r\n'.encode())
    for name, (filename, data) in files.items():
        out.write(f'--{boundary}\r\nContent-Disposition: form-data; name="{name}"; filename="{filename}"\r\n'
                  f"Content-Type: image/png\r\n\r\n".encode())
        out.write(data + b"\r\n")
    out.write(f"--{boundary}--\r\n".encode())
    return out.getvalue(), f"multipart/form-data; boundary={boundary}"


class Scenes:
    """The dev pair (00, 02) and variants of it that differ in one pixel (so each POST is a new scene)."""

    def __init__(self) -> None:
        meta = json.loads((DATA / "scene.json").read_text())
        frames = {f["name"]: f for f in meta["frames"]}
        self.poses = json.dumps({"convention": meta.get("convention", "opencv"),
                                 "c2w": [frames["00"]["c2w"], frames["02"]["c2w"]]})
        self.a = np.asarray(Image.open(DATA / frames["00"]["image"]).convert("RGB"))
        self.b = (DATA / frames["02"]["image"]).read_bytes()

    def variant(self, i: int) -> tuple[bytes, str]:
        a = self.a.copy()
        a[i // a.shape[1] % a.shape[0], i % a.shape[1]] ^= 1
        buf = io.BytesIO()
        Image.fromarray(a).save(buf, format="PNG", compress_level=1)
        return multipart({"poses": self.poses}, {"image_a": ("a.png", buf.getvalue()), "image_b": ("b.png", self.b)})


def post_scene(url: str, body: tuple[bytes, str]) -> tuple[int, dict, bytes]:
    return request(f"{url}/v1/scenes", "POST", body[0], {"Content-Type": body[1]})


def render_url(url: str, scene_id: str, i: int = 0, width: int = 512) -> str:
    c2w = np.eye(4)
    c2w[0, 3] = 0.01 * (i % 50)  # a new view each time
    return f"{url}/v1/scenes/{scene_id}/render?width={width}&c2w=" + ",".join(f"{v:g}" for v in c2w.ravel())


def closed_loop(work, seconds: float, clients: int) -> dict:
    """``clients`` threads calling ``work(i)`` back to back for ``seconds``; counts by status."""
    stop = time.monotonic() + seconds
    counter = iter(range(10**9))
    lock = threading.Lock()
    codes: dict[int, int] = {}
    replicas: set[str] = set()

    def loop() -> None:
        while time.monotonic() < stop:
            with lock:
                i = next(counter)
            status, headers, _ = work(i)
            with lock:
                codes[status] = codes.get(status, 0) + 1
                if HEADER in headers:
                    replicas.add(headers[HEADER])

    t0 = time.monotonic()
    threads = [threading.Thread(target=loop) for _ in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    elapsed = time.monotonic() - t0
    ok = sum(n for c, n in codes.items() if 200 <= c < 300)
    return {"ok": ok, "per_minute": round(60.0 * ok / elapsed, 1), "seconds": round(elapsed, 1),
            "codes": {str(k): v for k, v in sorted(codes.items())}, "replicas": len(replicas)}


def bench(url: str, seconds: float, clients: int) -> dict:
    scenes = Scenes()
    bodies = [scenes.variant(int(time.time()) * 1000 + i) for i in range(int(seconds) * 3)]  # more than are sent
    posts = closed_loop(lambda i: post_scene(url, bodies[i % len(bodies)]), seconds, clients)
    status, _, body = post_scene(url, scenes.variant(7))
    scene_id = json.loads(body)["id"]
    renders = closed_loop(lambda i: request(render_url(url, scene_id, i)), seconds, clients)
    return {"post_scene": posts, "render_512": renders, "load_avg": os.getloadavg()}


def wait_job(url: str, job_id: str, timeout: float, seen: set[str] | None = None) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        status, headers, body = request(f"{url}/v1/jobs/{job_id}")
        if seen is not None and HEADER in headers:
            seen.add(headers[HEADER])
        if status == 200 and json.loads(body)["status"] in ("done", "failed"):
            return json.loads(body)
        time.sleep(0.2)
    raise TimeoutError(f"job {job_id} not finished in {timeout} s")


def checks(url: str, store: Path) -> tuple[bool, dict]:
    out: dict = {}
    fails: list[str] = []

    def check(ok: bool, what: str) -> None:
        if not ok:
            fails.append(what)

    scenes = Scenes()
    status, _, body = post_scene(url, scenes.variant(4242))
    check(status == 201, f"POST scene -> {status} {body[:200]!r}")
    scene_id = json.loads(body)["id"]
    status, headers, body = request(render_url(url, scene_id))
    check(status == 200 and headers.get("content-type") == "image/png", f"render -> {status}")

    # a short refinement; status read repeatedly, answered by both replicas
    params = {"iterations": 5, "height": 64, "patience": 0}
    status, _, body = request(f"{url}/v1/scenes/{scene_id}/refine", "POST", json.dumps(params).encode(),
                              {"Content-Type": "application/json"})
    check(status == 202, f"refine -> {status} {body[:200]!r}")
    job = json.loads(body)
    seen: set[str] = set()
    done = wait_job(url, job["id"], 300, seen)
    for _ in range(40):
        if len(seen) >= 2:
            break
        seen.add(request(f"{url}/v1/jobs/{job['id']}")[1].get(HEADER, ""))
    out["job_status_replicas"] = sorted(seen)
    check(done["status"] == "done", f"refine job ended {done['status']}: {done.get('error')}")
    check(len(seen - {""}) >= 2, f"job status answered by {sorted(seen)} (want 2 replicas)")
    status, _, _ = request(render_url(url, done.get("scene_id") or "0" * 32))
    check(status == 200, f"render of the refined scene -> {status}")

    # a long refinement; kill -9 the replica that runs it
    long = {"iterations": 2000, "height": 256, "patience": 0, "cross_check": False}
    status, _, body = request(f"{url}/v1/scenes/{scene_id}/refine", "POST", json.dumps(long).encode(),
                              {"Content-Type": "application/json"})
    check(status == 202, f"long refine -> {status} {body[:200]!r}")
    long_id = json.loads(body)["id"]
    owner, deadline = None, time.monotonic() + 60
    while time.monotonic() < deadline:
        body = json.loads(request(f"{url}/v1/jobs/{long_id}")[2])
        if body.get("status") == "running" and body.get("progress", 0) > 0:
            owner = body.get("owner")
            break
        time.sleep(0.3)
    check(owner is not None, "the long job never reported progress")
    if owner is None:
        return not fails, {**out, "fails": fails}
    os.kill(int(owner["pid"]), signal.SIGKILL)
    killed_at = time.monotonic()
    out["killed"] = owner
    codes: dict[str, int] = {}
    answered_by: set[str] = set()
    final, to_failed = None, None
    i = 0
    while True:  # requests for 20 s after the kill, and until the job is reported finished (at most 90 s)
        elapsed = time.monotonic() - killed_at
        if elapsed >= 90 or (final is not None and elapsed >= 20):
            break
        i += 1
        for u in (f"{url}/v1/jobs/{long_id}", f"{url}/v1/scenes/{scene_id}", render_url(url, scene_id, i, 256)):
            status, headers, body = request(u, timeout=60)
            codes[str(status)] = codes.get(str(status), 0) + 1
            answered_by.add(headers.get(HEADER, "?"))
            if final is None and u.endswith(long_id) and status == 200 and json.loads(body)["status"] != "running":
                final, to_failed = json.loads(body), round(time.monotonic() - killed_at, 1)
        time.sleep(0.2)
    out["after_kill"] = {"codes": codes, "seconds_to_failed": to_failed, "answered_by": sorted(answered_by),
                         "job": None if final is None else {"status": final["status"], "error": final["error"]}}
    check(final is not None and final["status"] == "failed" and final["error"]["code"] == "replica_lost",
          f"killed job reported {final}")
    answered = sum(n for c, n in codes.items() if c != "0")
    check(answered == sum(codes.values()), f"requests without an HTTP answer after the kill: {codes}")
    errors = sum(n for c, n in codes.items() if not c.startswith("2"))
    check(errors <= 3, f"more than 3 non-2xx answers after the kill: {codes}")

    # a new refinement runs on a live replica and finishes
    again = {**long, "iterations": 3, "height": 64}
    status, _, body = request(f"{url}/v1/scenes/{scene_id}/refine", "POST", json.dumps(again).encode(),
                              {"Content-Type": "application/json"})
    check(status == 202 and wait_job(url, json.loads(body)["id"], 300)["status"] == "done", "refine after the kill")

    # every stored scene reads back whole, through the API and from disk
    ids = sorted(p.name for p in (store / "scenes").iterdir() if (p / "meta.json").is_file())
    bad = []
    for sid in ids:
        try:
            with np.load(store / "scenes" / sid / "gaussians.npz") as z:
                n = len(z["means"])
            meta = json.loads((store / "scenes" / sid / "meta.json").read_text())
            if meta["num_gaussians"] != n or request(f"{url}/v1/scenes/{sid}")[0] != 200:
                bad.append(sid)
        except Exception as exc:  # noqa: BLE001 - any read error is a corrupt scene
            bad.append(f"{sid}: {exc}")
    out["stored_scenes"], out["corrupt_or_unreadable"] = len(ids), bad
    check(not bad and len(ids) > 0, f"scenes not read back: {bad}")
    out["fails"] = fails
    return not fails, out


def wait_ready(url: str, replicas: int, timeout: float = 600.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        answers = [request(f"{url}/readyz", timeout=10) for _ in range(20)]
        if all(s == 200 for s, _, _ in answers) and len({h.get(HEADER) for _, h, _ in answers}) == replicas:
            return True
        time.sleep(2)
    return False


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("url")
    p.add_argument("store", type=Path)
    p.add_argument("phase", choices=["wait", "bench", "checks"])
    p.add_argument("--seconds", type=float, default=30.0)
    p.add_argument("--clients", type=int, default=3)
    p.add_argument("--replicas", type=int, default=1)
    args = p.parse_args()
    if args.phase == "wait":
        return 0 if wait_ready(args.url, args.replicas) else 1
    if args.phase == "bench":
        print(json.dumps(bench(args.url, args.seconds, args.clients)), flush=True)
        return 0
    ok, out = checks(args.url, args.store)
    print(json.dumps(out), flush=True)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

"""Measure the service end to end: POST /v1/scenes and GET render latency, and peak RSS.

    omnisplat-bench service --model MODEL.onnx [--height 512] [--repeats 5] [--json out.json] [--readme README.md]

Starts ``omnisplat serve`` as a subprocess on 127.0.0.1 (fresh temporary store), posts two
``height`` x 2 ``height`` panoramas (512 by default; ``--height 2880 --repeats 1`` gives a 5760x2880 pair's peak
memory; the dev scene when present, else synthetic ones) ``repeats`` times with
distinct options so each POST really reconstructs, then as often without poses (estimated from the
images, as for a hand-held capture; each time other pictures, a pixel apart), then the last of those again
with other options (the pose stage keeps a picture's features), then GETs ``repeats`` renders of each view
(a 1024-wide ERP and a 1280x720 90-degree perspective, from the dev scene's target pose when
present) and reads the server's peak RSS (VmHWM) from /proc. Prints a table of the medians with
the machine, date and load (before and after). Timings on a shared CPU are noisy.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench import DEV_DATA
from bench.report import readme_markers, update_readme

DEV_SCENE = DEV_DATA / "m3d_bedroom"


def free_port() -> int:
    """A TCP port on 127.0.0.1 that is free right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_ready(url: str, proc: subprocess.Popen, timeout_s: float, accept=None, poll_s: float = 0.1) -> None:
    """Poll ``url``/readyz until it answers 200 (or ``accept(response)`` is true) while the server process
    ``proc`` lives; RuntimeError when the process exits or ``timeout_s`` seconds pass first."""
    import httpx

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            r = httpx.get(url + "/readyz", timeout=2)
            if r.status_code == 200 or (accept is not None and accept(r)):
                return
        except httpx.TransportError:
            pass
        if proc.poll() is not None:
            break
        time.sleep(poll_s)
    raise RuntimeError(f"server did not become ready (exit {proc.poll()})")


def _target_pose(fallback: list) -> list:
    """The dev scene's first target camera (what the quality benches score), else ``fallback``."""
    scene = DEV_SCENE / "scene.json"
    if scene.is_file():
        meta = json.loads(scene.read_text())
        frames = {f["name"]: f for f in meta["frames"]}
        targets = meta["splits"][0].get("targets") or []
        if targets:
            return frames[targets[0]]["c2w"]
    return fallback


#: The rendered views: (row label, query parameters besides c2w).
VIEWS = (("GET ERP render, 1024 wide", {"width": 1024}),
         ("GET perspective render, 1280x720, 90 deg", {"projection": "perspective", "width": 1280, "height": 720,
                                                       "fov_deg": 90.0}))


def post_inputs(height: int, fmt: str = "PNG", variant: int = 0) -> tuple[bytes, bytes, list, list]:
    """(image A, image B, c2w A, c2w B) for a POST, as PNG or JPEG (quality 92, what cameras write): the dev
    scene's first split at ``height`` if present, else noise. ``variant`` k > 0 inverts pixel (0, k) of both
    images: other pictures to the service, whose pose stage keeps the features of pictures it has seen."""
    from PIL import Image

    def encode(arr: np.ndarray) -> bytes:
        if variant:
            arr = arr.copy()
            arr[0, variant] = 255 - arr[0, variant]
        buf = io.BytesIO()
        Image.fromarray(arr).save(buf, format=fmt, **({"quality": 92} if fmt == "JPEG" else {}))
        return buf.getvalue()

    scene = DEV_SCENE / "scene.json"
    if scene.is_file():
        meta = json.loads(scene.read_text())
        frames = {f["name"]: f for f in meta["frames"]}
        a, b = (frames[n] for n in meta["splits"][0]["references"])
        imgs = [np.asarray(Image.open(DEV_SCENE / f["image"]).convert("RGB").resize((2 * height, height)))
                for f in (a, b)]
        return encode(imgs[0]), encode(imgs[1]), a["c2w"], b["c2w"]
    rng = np.random.default_rng(0)
    img = (rng.random((height, 2 * height, 3)) * 255).astype(np.uint8)
    eye, moved = np.eye(4), np.eye(4)
    moved[0, 3] = 0.5
    return encode(img), encode(np.roll(img, 8, axis=1)), eye.tolist(), moved.tolist()


def _peak_rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return None


def _server_timing(header: str, name: str) -> float:
    """Seconds of the ``name`` entry of a Server-Timing header (NaN when absent)."""
    for part in header.split(","):
        key, _, dur = part.strip().partition(";dur=")
        if key == name and dur:
            return float(dur) / 1000.0
    return float("nan")


def _table(result: dict, machine: str) -> str:
    """The medians as a markdown table, with the machine line and the load at the end."""
    rows = ["| request | median |", "|---|---|",
            f"| POST {result['inputs']} | {result['post_scene_seconds']['median']:.2f} s |",
            f"| POST another pair without poses (estimated from the images) | "
            f"{result['post_without_poses_seconds']['median']:.2f} s (poses stage "
            f"{result['post_without_poses_seconds']['median_poses_stage']:.2f} s) |",
            f"| POST that pair again without poses, other options (its features kept) | "
            f"{result['post_again_without_poses_seconds']['median']:.2f} s (poses stage "
            f"{result['post_again_without_poses_seconds']['median_poses_stage']:.2f} s) |"]
    for label, r in result["renders"].items():
        rows.append(f"| {label} | {r['median_seconds']:.2f} s (render stage {r['median_render_stage_seconds']:.2f} s) |")
    rss = result["peak_rss_mb"]
    rows.append(f"| server peak RSS (VmHWM) after these | {'n/a' if rss is None else f'{rss / 1024:.2f} GB'} |")
    return "\n".join(rows + ["", f"{result['num_gaussians']} Gaussians; {machine}; load average at the end "
                                  f"{result['load_average_1_5_15min_at_end']}"])


def main(argv: list[str] | None = None) -> int:
    import httpx

    p = argparse.ArgumentParser(prog="omnisplat-bench service", description=__doc__.splitlines()[0])
    p.add_argument("--model", type=Path, required=True, help="ONNX model to serve")
    p.add_argument("--height", type=int, default=512, help="panorama height (width = 2 x height)")
    p.add_argument("--format", choices=("png", "jpeg"), default="png", help="how the panoramas are sent")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--json", type=Path, help="write the results here too")
    p.add_argument("--readme", type=Path, action="append", default=[],
                   help="markdown file(s) whose marked block bench:service-HxW gets the table (README.md, "
                        "docs/benchmarks.md); repeatable")
    args = p.parse_args(argv)
    from bench.machine import machine_info, machine_line

    machine = machine_info()
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    with tempfile.TemporaryDirectory() as store:
        cmd = [sys.executable, "-m", "service.cli", "serve", "--no-build", "--model", str(args.model),
               "--store", store, "--port", str(port), "--log-level", "warning"]
        proc = subprocess.Popen(cmd, cwd=Path(__file__).resolve().parents[1])
        try:
            t0 = time.perf_counter()
            try:
                wait_ready(url, proc, 300)
            except RuntimeError as exc:
                raise SystemExit(str(exc)) from None
            ready_s = time.perf_counter() - t0
            a, b, ca, cb = post_inputs(args.height, args.format.upper())
            poses = json.dumps({"convention": "opencv", "c2w": [ca, cb]})
            post_s, stage_sums, sid, n = [], {}, None, 0
            render_s = {label: [] for label, _ in VIEWS}
            render_stage = {label: [] for label, _ in VIEWS}
            with httpx.Client(base_url=url, timeout=600) as c:
                def post(fields: dict, far: float, label: str, images: tuple = (a, b)) -> dict:
                    """One POST of a pair; a distinct far plane -> a distinct scene id -> a real reconstruction."""
                    t = time.perf_counter()
                    ia, ib = images
                    r = c.post("/v1/scenes", files={"image_a": (f"a.{args.format}", ia), "image_b": (f"b.{args.format}", ib)},
                               data={**fields, "options": json.dumps({"far": far})})
                    seconds = time.perf_counter() - t
                    r.raise_for_status()
                    print(f"{label}: {seconds:.2f} s", file=sys.stderr)
                    return {**r.json(), "seconds": seconds}

                for i in range(args.repeats):
                    body = post({"poses": poses}, 20.0 + 0.01 * i, f"POST {i + 1}/{args.repeats}")
                    post_s.append(body["seconds"])
                    sid, n = body["id"], body["num_gaussians"]
                    for k, v in body["timings"].items():
                        stage_sums.setdefault(k, []).append(v)
                unposed_s, pose_stage, again_s, again_stage = [], [], [], []
                for i in range(args.repeats):  # what a user without poses waits for: new pictures, poses estimated
                    pa, pb = post_inputs(args.height, args.format.upper(), variant=i + 1)[:2]
                    body = post({}, 30.0 + 0.01 * i, f"POST without poses {i + 1}/{args.repeats}", (pa, pb))
                    unposed_s.append(body["seconds"])
                    pose_stage.append(body["timings"]["poses"])
                for i in range(args.repeats):  # the last pair again with other options: its features are kept
                    body = post({}, 40.0 + 0.01 * i, f"POST again without poses {i + 1}/{args.repeats}", (pa, pb))
                    again_s.append(body["seconds"])
                    again_stage.append(body["timings"]["poses"])
                c2w = ",".join(str(v) for v in np.asarray(_target_pose(ca), dtype=float).ravel())
                for label, params in VIEWS:
                    for i in range(args.repeats):
                        t = time.perf_counter()
                        r = c.get(f"/v1/scenes/{sid}/render", params={"c2w": c2w, **params})
                        render_s[label].append(time.perf_counter() - t)
                        r.raise_for_status()
                        render_stage[label].append(_server_timing(r.headers.get("server-timing", ""), "render"))
                        print(f"{label} {i + 1}/{args.repeats}: {render_s[label][-1]:.2f} s", file=sys.stderr)
                info = c.get("/v1/info").json()
            result = {
                "model": {k: info["model"].get(k) for k in ("name", "version", "sha256")},
                "inputs": f"two {args.height}x{2 * args.height} {args.format.upper()} panoramas"
                          + (" (m3d_bedroom, resized)" if (DEV_SCENE / "scene.json").is_file() else " (synthetic)"),
                "num_gaussians": n,
                "ready_seconds": round(ready_s, 2),
                "post_scene_seconds": {"median": statistics.median(post_s), "all": post_s},
                "post_stage_median_seconds": {k: statistics.median(v) for k, v in stage_sums.items()},
                "post_without_poses_seconds": {"median": statistics.median(unposed_s), "all": unposed_s,
                                               "median_poses_stage": statistics.median(pose_stage)},
                "post_again_without_poses_seconds": {"median": statistics.median(again_s), "all": again_s,
                                                     "median_poses_stage": statistics.median(again_stage)},
                "renders": {label: {"params": params, "median_seconds": statistics.median(render_s[label]),
                                    "all_seconds": render_s[label],
                                    "median_render_stage_seconds": statistics.median(render_stage[label])}
                            for label, params in VIEWS},
                "peak_rss_mb": _peak_rss_mb(proc.pid),
                "machine": machine,
                "load_average_1_5_15min_at_end": [round(x, 2) for x in os.getloadavg()],
            }
        finally:
            proc.terminate()
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
    text = json.dumps(result, indent=2)
    print(text)
    table = _table(result, machine_line(machine))
    print(table)
    if args.json:
        args.json.write_text(text + "\n")
    name = f"service-{args.height}x{2 * args.height}" + ("-jpeg" if args.format == "jpeg" else "")
    command = f"service --model MODEL.onnx --height {args.height}" + (" --format jpeg" if args.format == "jpeg" else "")
    start, end = readme_markers(name, command)
    for readme in args.readme:
        if not update_readme(readme, f"{start}\n{table}\n{end}", name, command):
            print(f"{readme}: no {start.split(' (')[0]} marker; not written", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""``omnisplat-bench poses``: poses optional, measured against the scene files' poses.

Per split (references A, B): estimate B's pose from the two images (:mod:`service.poses`,
scale from A's camera height), compare with the scene's relative pose (rotation error deg,
translation direction error deg, scale error %), then build the scene as the service does
(default model, :func:`service.pipeline.build_scene`) with the given, the refined
(``refine_poses``) and the estimated poses and render every target with plain compositing
(ERP ``method="direct"``: colour over black, no division by alpha). Targets are placed in the
estimated frame by the similarity that maps the scene's A onto the estimated A and its baseline
onto the estimated one. Writes ``poses.json`` and ``poses.md`` into ``--out``.

``--pairs-within M``: pose errors only (no model, no rendering) on every pair of frames at most
M metres apart; writes ``poses_pairs.json``.

    omnisplat-bench poses --data ../shared/data/m3d_bedroom ../shared/data/zind_room09
    omnisplat-bench poses --data ../shared/data/bedroom_theta --pairs-within 2 --camera-height 2.2
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from bench import metrics
from bench.baselines import copy_nearest
from bench.quality import resize_erp_box
from rasterizer.geometry import grid_directions
from rasterizer.relative_pose import floor_scale
from rasterizer.render import render
from rasterizer.scene_folder import Frame, SceneFolder, load_scene

DEFAULT_OUT = Path(__file__).resolve().parents[1] / "docs" / "bench"


def _log(msg: str) -> None:
    print(f"[bench poses] {msg}", file=sys.stderr, flush=True)


def camera_height(scene: SceneFolder, frame: Frame) -> float:
    """Metres of ``frame``'s camera above the floor: from its depth map when it has one (the floor
    rule of :func:`rasterizer.relative_pose.floor_scale` on every 4th pixel), else its world z
    (z-up scenes with the floor at z = 0, as zind). Exits with a message where neither gives a
    height (a structure-from-motion frame without depth: pass ``--camera-height``)."""
    depth = frame.depth()
    if depth is not None:
        pts = (grid_directions("erp", *depth.shape) * depth[..., None])[::4, ::4].reshape(-1, 3)
        return 1.0 / floor_scale(pts[depth[::4, ::4].reshape(-1) > 0], 1.0)[0]
    h = float(frame.c2w[2, 3])
    if not h > 0:
        raise SystemExit(f"{scene.name}: frame {frame.name} has no depth map and its world z is {h:g}, "
                         "so the scene gives no camera height; pass --camera-height")
    return h


def pose_errors(rel_true: np.ndarray, rel_est: np.ndarray) -> dict:
    """Rotation error (deg), translation direction error (deg), scale error (%) of B relative to A."""
    cos = (np.trace(rel_true[:3, :3].T @ rel_est[:3, :3]) - 1) / 2
    t, e = rel_true[:3, 3], rel_est[:3, 3]
    return {"rotation_deg": float(np.degrees(np.arccos(np.clip(cos, -1, 1)))),
            "direction_deg": float(np.degrees(np.arccos(np.clip(t @ e / np.linalg.norm(t) / np.linalg.norm(e), -1, 1)))),
            "scale_pct": float((np.linalg.norm(e) / np.linalg.norm(t) - 1) * 100)}


def into_estimate(c2w_a: np.ndarray, c2w: np.ndarray, scale: float) -> np.ndarray:
    """A scene-frame pose in the estimate's frame (A = I, lengths times ``scale``)."""
    m = np.linalg.inv(c2w_a) @ c2w
    m[:3, 3] *= scale
    return m


def pair_rows(root: Path, max_m: float, height: float | None = None) -> list[dict]:
    """Pose errors of the estimate on every pair of frames at most ``max_m`` apart (no rendering).

    The scale comes from ``height`` (metres above the floor for every frame) or the bench's
    :func:`camera_height` of the first frame; errors compare the estimate's B relative to its A
    with the scene's."""
    from service.errors import ServiceError
    from service.poses import PoseOptions, estimate_poses, prepare

    scene = load_scene(root)
    names = list(scene.frames)
    prepared: dict = {}
    rows = []
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            fa, fb = scene.frames[a], scene.frames[b]
            rel = np.linalg.inv(fa.c2w) @ fb.c2w
            dist = float(np.linalg.norm(rel[:3, 3]))
            if dist > max_m:
                continue
            for n in (a, b):
                if n not in prepared:  # features and gravity once per frame, with the file's XMP
                    f = scene.frames[n]
                    prepared[n] = prepare(f.image(), f.image_path.read_bytes())
            pa, pb = prepared[a], prepared[b]
            h = height if height is not None else camera_height(scene, fa)
            row = {"scene": scene.name, "references": [a, b], "baseline_m": dist, "camera_height_m": h}
            t0 = time.perf_counter()
            try:
                c2w_a, c2w_b, info = estimate_poses(pa.gray, pb.gray, PoseOptions(camera_height=h), prepared=(pa, pb))
            except ServiceError as exc:
                row["estimate"] = {"seconds": time.perf_counter() - t0, "error": exc.code, "message": exc.message}
            else:
                est = np.linalg.inv(c2w_a) @ c2w_b
                row["estimate"] = {"seconds": time.perf_counter() - t0, **pose_errors(rel, est),
                                   "inliers": info["inliers"], "method": info["method"],
                                   "residual_tilt_deg": info.get("residual_tilt_deg"),
                                   "gravity": [{k: g[k] for k in ("source", "tilt_deg")} for g in info["gravity"]],
                                   "scale": info.get("scale")}
            _log(json.dumps(row))
            rows.append(row)
    return rows


def pairs_markdown(rows: list[dict], rot_deg: float = 1.0, dir_deg: float = 2.0, scale_pct: float = 15.0) -> str:
    """Per pair: rotation / travel direction / baseline errors and the floor that set the scale (``dense`` sweep or
    triangulated ``points``, with the scale step's seconds), then the share within the targets."""
    lines = ["| scene pair (baseline) | rot err deg | dir err deg | baseline est / true | inliers | method | floor (s) | s |",
             "|---|---|---|---|---|---|---|---|"]
    floor_s = []
    ok = {"rot": 0, "dir": 0, "scale": 0}
    for r in rows:
        e = r["estimate"]
        head = f"| {r['scene']} {'+'.join(r['references'])} ({r['baseline_m']:.2f} m) "
        if "error" in e:
            lines.append(head + f"| 422 `{e['error']}` | | | | | | {e['seconds']:.1f} |")
            continue
        ok["rot"] += e["rotation_deg"] <= rot_deg
        ok["dir"] += e["direction_deg"] <= dir_deg
        ok["scale"] += abs(e["scale_pct"]) <= scale_pct
        scale = e.get("scale") or {}
        floor = f"{scale['floor']} ({scale['seconds']:.2f})" if "floor" in scale else ""
        if scale.get("floor") == "dense":
            floor_s.append(scale["seconds"])
        lines.append(head + f"| {e['rotation_deg']:.2f} | {e['direction_deg']:.2f} | {1 + e['scale_pct'] / 100:.2f}x "
                     f"| {e['inliers']} | {e['method']} | {floor} | {e['seconds']:.1f} |")
    n = max(len(rows), 1)
    lines += ["", f"{len(rows)} pairs: rotation <= {rot_deg:g} deg on {ok['rot'] / n:.0%}, travel direction <= "
              f"{dir_deg:g} deg on {ok['dir'] / n:.0%}, baseline within {scale_pct:g}% on {ok['scale'] / n:.0%} "
              "(a 422 counts as a miss)"]
    if floor_s:
        lines.append(f"Floor from the dense sweep on {len(floor_s)} pairs: median {np.median(floor_s):.2f} s per pair "
                     "(the scale step, camera_height given)")
    return "\n".join(lines) + "\n"


def run(data: list[Path], out: Path, width: int, threads: int, splits: list[int] | None = None,
        height: float | None = None) -> dict:
    from service.config import Settings
    from service.encoder import OnnxEncoder
    from service.errors import ServiceError
    from service.model_files import ensure_model
    from service.pipeline import PipelineOptions, build_scene
    from service.poses import PoseOptions, estimate_poses, refine_poses

    model = ensure_model(Settings().resolved_model_path, build_if_missing=True)
    encoder = OnnxEncoder(model, threads=threads)
    options = PipelineOptions.from_dict({})
    rows = []

    def psnrs(g, targets, to_frame):
        res = {}
        for name, frame in targets:
            target = resize_erp_box(frame.image(), width)
            for method in ("direct", "yinyang"):
                pred = np.clip(render(g, to_frame(frame.c2w), projection="erp", width=width, method=method).colour, 0, 1)
                res.setdefault(method, {})[name] = metrics.psnr(pred, target)
                res.setdefault(method + "_above_nadir", {})[name] = metrics.psnr_above_nadir(pred, target)
        return res

    for root in data:
        scene = load_scene(root)
        for si, split in enumerate(scene.splits):
            if splits is not None and si not in splits:
                continue
            fa, fb = (scene.frames[n] for n in split.references)
            ia, ib = fa.image(), fb.image()
            targets = [(n, scene.frames[n]) for n in split.targets]
            rel = np.linalg.inv(fa.c2w) @ fb.c2w
            row = {"scene": scene.name, "split": si, "references": list(split.references),
                   "baseline_m": float(np.linalg.norm(rel[:3, 3])), "targets": list(split.targets)}
            h = height if height is not None else camera_height(scene, fa)
            row["camera_height_m"] = h
            refs = [(ia, fa.c2w), (ib, fb.c2w)]
            row["copy_nearest"] = {n: metrics.psnr(copy_nearest(refs, f.c2w, width // 2, width),
                                                   resize_erp_box(f.image(), width))
                                   for n, f in targets}
            t0 = time.perf_counter()
            g = build_scene(encoder, ia, ib, fa.c2w, fb.c2w, options).gaussians
            row["given"] = psnrs(g, targets, lambda c: c)
            row["build_s"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            c2w_b_ref, info = refine_poses(ia, ib, fa.c2w, fb.c2w)
            row["refine"] = {"seconds": time.perf_counter() - t0, **info}
            g = build_scene(encoder, ia, ib, fa.c2w, c2w_b_ref, options).gaussians
            row["refined"] = psnrs(g, targets, lambda c: c)
            t0 = time.perf_counter()
            try:
                c2w_a_est, c2w_b, info = estimate_poses(ia, ib, PoseOptions(camera_height=h),
                                                        (fa.image_path.read_bytes(), fb.image_path.read_bytes()))
            except ServiceError as exc:
                row["estimate"] = {"seconds": time.perf_counter() - t0, "error": exc.code, "message": exc.message}
                _log(f"{scene.name} split {si}: {exc.code}: {exc.message}")
                rows.append(row)
                continue
            rel_est = np.linalg.inv(c2w_a_est) @ c2w_b
            row["estimate"] = {"seconds": time.perf_counter() - t0, **pose_errors(rel, rel_est), "inliers": info["inliers"],
                               "residual_deg": info["residual_deg"]}
            s = np.linalg.norm(rel_est[:3, 3]) / np.linalg.norm(rel[:3, 3])
            g = build_scene(encoder, ia, ib, c2w_a_est, c2w_b, options).gaussians
            row["estimated"] = psnrs(g, targets, lambda c: c2w_a_est @ into_estimate(fa.c2w, c, s))
            _log(json.dumps(row))
            rows.append(row)
    out.mkdir(parents=True, exist_ok=True)
    (out / "poses.json").write_text(json.dumps(rows, indent=1) + "\n")
    (out / "poses.md").write_text(markdown(rows))
    return {"rows": rows}


def _mean(d: dict | None, method: str | None = "direct") -> str:
    if d and method:
        return f"{np.mean(list(d[method].values())):.2f} / {np.mean(list(d['yinyang'].values())):.2f}"
    return f"{np.mean(list(d.values())):.2f}" if d else "-"


def markdown(rows: list[dict]) -> str:
    """Per split: pose errors of the estimate, then mean PSNR (dB, "plain / normalised") per pose source;
    then PSNR per target."""
    lines = ["| scene split (refs, baseline) | rot err deg | dir err deg | scale err % | inliers | s | "
             "copy nearest | given | given + refine_poses | estimated |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        e = r["estimate"]
        head = f"| {r['scene']} {r['split']} ({', '.join(r['references'])}, {r['baseline_m']:.2f} m) "
        if "error" in e:
            pose = f"| 422 `{e['error']}` | | | | {e['seconds']:.1f} "
        else:
            pose = (f"| {e['rotation_deg']:.2f} | {e['direction_deg']:.2f} | {e['scale_pct']:+.1f} | {e['inliers']} "
                    f"| {e['seconds']:.1f} ")
        lines.append(head + pose + f"| {_mean(r['copy_nearest'], None)} | {_mean(r['given'])} | {_mean(r['refined'])} "
                     f"| {_mean(r.get('estimated'))} |")
    lines += ["", "| target (split) | copy nearest | given plain / norm. | refined plain / norm. | estimated plain / norm. |",
              "|---|---|---|---|---|"]
    for r in rows:
        for t in r["targets"]:
            cells = [f"{r[k]['direct'][t]:.2f} / {r[k]['yinyang'][t]:.2f}" if k in r else "-"
                     for k in ("given", "refined", "estimated")]
            lines.append(f"| {r['scene']} {t} ({r['split']}) | {r['copy_nearest'][t]:.2f} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="omnisplat-bench poses", description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, nargs="+", required=True, help="scene folders")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    p.add_argument("--width", type=int, default=1024, help="render width (the targets' width)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--splits", type=int, nargs="+", default=None, help="only these split indices (default: all)")
    p.add_argument("--pairs-within", type=float, default=None, metavar="M",
                   help="pose errors only (no rendering) on every pair of frames at most M metres apart")
    p.add_argument("--camera-height", type=float, default=None,
                   help="metres above the floor for every frame (default: from the scene)")
    args = p.parse_args(argv)
    if args.pairs_within is not None:
        rows = [r for root in args.data for r in pair_rows(root, args.pairs_within, args.camera_height)]
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "poses_pairs.json").write_text(json.dumps(rows, indent=1) + "\n")
        print(pairs_markdown(rows))
        return 0
    res = run(args.data, args.out, args.width, args.threads, args.splits, args.camera_height)
    print(markdown(res["rows"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

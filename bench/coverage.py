"""``omnisplat-bench coverage``: how opaque the reconstructed surfaces are, and quality plain vs V/A.

For every dev split: reconstruct with the shipped encoder (or ``--model``),
compact as the service does by default, and for both the raw and the
compacted Gaussians measure the accumulated alpha (mean, fraction >= 0.99)
of direct ERP renders at both reference poses and every target, and of
perspective views (640x480, 90 deg) at the first target, yaw 0/90/180/270;
PSNR plain (over black, no division by alpha) and V/A (divided by alpha)
at the targets, plain also above the nadir cap (``bench.metrics.psnr_above_nadir``), and
copying the nearest reference for comparison. Where the scene has GT depth, target pixels that neither
reference sees (genuine disocclusions: the GT surface point is hidden in
both references' GT depth) are counted and left out of a second fraction.

    omnisplat-bench coverage [--data DIR ...] [--model M.onnx] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from bench import DEV_DATA
from bench.baselines import copy_nearest
from bench.metrics import psnr, psnr_above_nadir
from rasterizer import geometry as geo
from rasterizer.compaction import CompactionOptions, Provenance, compact
from rasterizer.render import render
from rasterizer.scene_folder import load_scene
from rasterizer.view_colour import DEFAULT_SH_DEGREE
from rasterizer.yin_yang import resize_erp

from .models import bench_model

#: Accumulated alpha that counts as covered.
COVERED = 0.99
#: Perspective views: size, field of view and yaws (degrees about the camera's vertical axis).
PERSPECTIVE = (640, 480, 90.0)
YAWS = (0, 90, 180, 270)
#: A target's GT surface point is seen by a reference when its range there is within this fraction.
VISIBLE_TOL = 0.03


def _log(msg: str) -> None:
    print(f"[bench coverage] {msg}", file=sys.stderr, flush=True)


def yaw_pose(c2w: np.ndarray, deg: float) -> np.ndarray:
    """c2w turned by ``deg`` about its own y axis (OpenCV: down), 4x4."""
    a = np.deg2rad(deg)
    rot = np.eye(4)
    rot[[0, 0, 2, 2], [0, 2, 0, 2]] = np.cos(a), np.sin(a), -np.sin(a), np.cos(a)
    return np.asarray(c2w, float) @ rot


def _erp_pixel(d: np.ndarray, height: int, width: int):
    """(row, col) float pixel coordinates of camera-frame directions d (..., 3) on an ERP."""
    lat, lon = geo.lat_lon_from_direction(d)
    return (np.pi / 2 - lat) / np.pi * height - 0.5, (lon + np.pi) / (2 * np.pi) * width - 0.5


def perspective_crop(erp: np.ndarray, yaw_deg: float, width: int, height: int, fov_deg: float) -> np.ndarray:
    """(height, width, 3) perspective view, bilinear from an ERP taken at the same centre, yawed by ``yaw_deg``."""
    from scipy.ndimage import map_coordinates

    d = geo.pinhole_directions(width, height, fov_deg).reshape(-1, 3) @ yaw_pose(np.eye(4), yaw_deg)[:3, :3].T
    row, col = _erp_pixel(d, *erp.shape[:2])
    out = [map_coordinates(np.pad(erp[..., c], ((0, 0), (1, 1)), mode="wrap"), [row, col + 1], order=1,
                           mode="nearest") for c in range(3)]
    return np.stack(out, -1).reshape(height, width, 3).astype(np.float32)


def disoccluded(scene, target: str, references, height: int, width: int) -> np.ndarray | None:
    """(height, width) bool: target ERP pixels whose GT surface point no reference sees (None: no GT depth)."""
    if not scene.has_depth:
        return None
    tgt = scene.frames[target]
    depth = resize_erp(tgt.depth()[..., None], height, width)[..., 0]
    ray = geo.grid_directions("erp", height, width)
    pts = tgt.c2w[:3, 3] + (depth[..., None] * ray) @ tgt.c2w[:3, :3].T
    seen = np.zeros((height, width), bool)
    for name in references:
        ref = scene.frames[name]
        ref_depth = ref.depth()
        p = geo.world_to_camera(pts.reshape(-1, 3), ref.c2w)
        rng = np.linalg.norm(p, axis=-1)
        row, col = _erp_pixel(p, *ref_depth.shape)
        r = np.clip(np.rint(row), 0, ref_depth.shape[0] - 1).astype(int)
        c = np.rint(col).astype(int) % ref_depth.shape[1]
        there = ref_depth[r, c]
        seen |= (np.abs(rng - there) <= VISIBLE_TOL * there).reshape(height, width)
    return ~seen & (depth > 0)


def alpha_stats(alpha: np.ndarray, mask: np.ndarray | None = None) -> dict:
    """Mean accumulated alpha and the fraction >= COVERED (over ``mask`` when given)."""
    a = alpha if mask is None else alpha[mask]
    return {"mean_alpha": float(a.mean()), "covered": float((a >= COVERED).mean())}


def measure(g, scene, split, width: int = 1024, perspective: bool = True, copy: bool = True) -> dict:
    """Alpha statistics and PSNR of Gaussians ``g`` at one split's reference and target poses; ``copy``:
    also copying the nearest reference at the targets (independent of ``g``)."""
    out: dict = {"erp": {}, "perspective": {}}
    refs = [(scene.frames[n].image(), scene.frames[n].c2w) for n in split.references] if copy else None
    for name in list(split.references) + list(split.targets):
        frame = scene.frames[name]
        plain = render(g, frame.c2w, projection="erp", width=width, method="direct")
        rec = {"role": "reference" if name in split.references else "target", **alpha_stats(plain.alpha)}
        gt = resize_erp(frame.image(), width // 2, width)
        rec["psnr_plain"] = psnr(plain.colour, gt)  # at a reference: how well the scene shows its own image
        rec["psnr_plain_above_nadir"] = psnr_above_nadir(plain.colour, gt)
        if name in split.targets:
            if copy:
                nearest = copy_nearest(refs, frame.c2w, width // 2, width)
                rec.update(psnr_copy_nearest=psnr(nearest, gt),
                           psnr_copy_nearest_above_nadir=psnr_above_nadir(nearest, gt))
            va = render(g, frame.c2w, projection="erp", width=width)
            rec.update(psnr_va=psnr(va.colour, gt),
                       psnr_yinyang_plain=psnr(va.colour * va.alpha[..., None], gt))
            hole = disoccluded(scene, name, split.references, width // 2, width)
            if hole is not None:
                rec["disoccluded"] = float(hole.mean())
                rec["covered_seen"] = alpha_stats(plain.alpha, ~hole)["covered"]
        out["erp"][name] = rec
    if perspective and split.targets:
        name = split.targets[0]
        frame = scene.frames[name]
        w, h, fov = PERSPECTIVE
        for yaw in YAWS:
            view = render(g, yaw_pose(frame.c2w, yaw), projection="perspective", width=w, height=h, fov_deg=fov)
            gt = perspective_crop(frame.image(), yaw, w, h, fov)
            out["perspective"][f"{name} yaw {yaw}"] = {**alpha_stats(view.alpha), "psnr_plain": psnr(view.colour, gt)}
    return out


def run(data: list[Path], model: Path | None, threads: int = 2, sh_degree: int = DEFAULT_SH_DEGREE,
        rig_cap_deg: float | None = None) -> list[dict]:
    """Measure every split of ``data`` with scenes of the given colour model and rig cap (encoder options)."""
    from service.encoder import OnnxEncoder

    enc = OnnxEncoder(model or bench_model(512, 1024, 64, log=_log), threads=threads)
    results = []
    for folder in data:
        scene = load_scene(folder)
        for si, split in enumerate(scene.splits):
            fa, fb = (scene.frames[n] for n in split.references)
            t = time.perf_counter()
            rec = enc.reconstruct(fa.image(), fb.image(), fa.c2w, fb.c2w, sh_degree=sh_degree, rig_cap_deg=rig_cap_deg)
            post = time.perf_counter() - t
            prov = Provenance.from_reconstruction(rec, fa.c2w, fb.c2w)
            t = time.perf_counter()
            small, _ = compact(rec.gaussians, prov, CompactionOptions())
            t_compact = time.perf_counter() - t
            entry = {"scene": scene.name, "split": si, "references": list(split.references),
                     "targets": list(split.targets), "model": enc.metadata.get("version"),
                     "sh_degree": int(rec.gaussians.sh_degree), "rig_cap_deg": rec.info["rig_cap_deg"],
                     "reconstruct_s": post, "compact_s": t_compact,
                     "count": len(rec.gaussians), "count_compacted": len(small),
                     "opacity_median": float(np.median(rec.gaussians.opacities)),
                     "raw": measure(rec.gaussians, scene, split),
                     "compacted": measure(small, scene, split, perspective=False, copy=False)}
            _log(f"{scene.name} {split.references}: {len(rec.gaussians)} -> {len(small)} Gaussians")
            results.append(entry)
    return results


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="omnisplat-bench coverage", description=__doc__.split("\n\n")[0])
    p.add_argument("--data", nargs="+", type=Path, default=[DEV_DATA / "m3d_bedroom", DEV_DATA / "zind_room09"])
    p.add_argument("--model", type=Path, default=None, help="ONNX model (default: the shipped quality preset)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json", type=Path, default=None, help="also write the results here")
    p.add_argument("--sh-degree", type=int, default=DEFAULT_SH_DEGREE,
                   help="colour model of the scenes (default 1: view-dependent; 0: one colour)")
    p.add_argument("--rig-cap-deg", type=float, default=None,
                   help="re-colour the pixels this many degrees around each camera's nadir (default: the "
                        "service's automatic cap, 20 where both references show a rig, else 0)")
    args = p.parse_args(argv)
    results = run(args.data, args.model, args.threads, args.sh_degree, args.rig_cap_deg)
    text = json.dumps(results, indent=1)
    if args.json:
        args.json.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

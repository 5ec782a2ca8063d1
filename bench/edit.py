"""Multiview-consistent selection: mask carried through the encoder's matches vs pseudo ground truth.

For each point prompt on reference A (m3d_bedroom 00) the selection gives masks in A and B (02). Pseudo
ground truth in B = A's mask carried through the *GT* range maps: a B pixel takes A's mask value at the
A pixel its GT point projects to, where A's GT range there agrees (3% relative; else the pixel is void:
A does not see it). IoU over non-void B pixels, cos-latitude weighted. Baselines on the same A masks:
(a) the same pixels in B, (b) dense optical flow B -> A (OpenCV DIS, medium preset) on the ERPs.
Selections run on the stored correspondences (``edit.npz`` read back: float16 ranges), as the
service's do. Also: stored bytes of the correspondences, index build and per-selection seconds,
agreement of the automatic segments across views at GT-matched pixels, and one picture (prompt, both
masks, the target view after remove and after recolor).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from rasterizer import geometry as geo
from rasterizer.scene_folder import load_scene

from . import DEV_DATA
from .machine import machine_info, machine_line
from .report import readme_markers, update_readme, write_json

DEFAULT_DATA = DEV_DATA / "m3d_bedroom"
DEFAULT_OUT = Path("docs/bench")
#: Point prompts (u, v) on reference A (00), picked by eye on the image: one object each, 1-4 clicks on its parts.
PROMPTS = {
    "bed": [(0.03, 0.66), (0.08, 0.64), (0.12, 0.64), (0.05, 0.72)], "picture_left": [(0.12, 0.45)],
    "painting": [(0.69, 0.43)], "lamp": [(0.685, 0.58), (0.695, 0.66), (0.70, 0.71)],
    "table": [(0.66, 0.77), (0.72, 0.80), (0.78, 0.78)], "chair": [(0.845, 0.66), (0.87, 0.65)],
    "closet_door": [(0.22, 0.50)], "window": [(0.45, 0.35)], "rug": [(0.05, 0.84), (0.12, 0.86), (0.17, 0.82)],
    "door": [(0.95, 0.50)],
}
FIGURE_PROMPT = "door"
VISIBLE_TOL = 0.03


def _log(msg: str) -> None:
    print(f"[bench edit] {msg}", flush=True)


def gt_carry(depth_b: np.ndarray, depth_a: np.ndarray, c2w_b, c2w_a) -> tuple[np.ndarray, np.ndarray]:
    """For every B pixel (H, W): flat index of the A pixel its GT point lands on, and whether A sees it."""
    h, w = depth_b.shape
    p = geo.grid_directions("erp", h, w) * depth_b[..., None] @ np.asarray(c2w_b)[:3, :3].T + np.asarray(c2w_b)[:3, 3]
    q = geo.world_to_camera(p, c2w_a)
    col, row = geo.project_to_grid("erp", q, h, w)
    c = np.mod(np.rint(col).astype(np.int64), w)
    r = np.clip(np.rint(row).astype(np.int64), 0, h - 1)
    dist = np.linalg.norm(q, axis=-1)
    seen = depth_a[r, c]
    visible = (depth_b > 0) & (seen > 0) & (np.abs(seen - dist) <= VISIBLE_TOL * dist)
    return r * w + c, visible


def gt_matches(edit, depths, c2ws) -> np.ndarray:
    """``matches`` (2, G, H, W, 5) in the encoder's layout from GT range maps (ERP, metres), all consistent:
    what the graph would output with exact depth (the oracle column)."""
    from rasterizer.yin_yang import erp_to_yin_yang

    h, w = edit.height, edit.width
    out = np.zeros((2, len(edit.grids), h, w, 5), np.float32)
    for v in range(2):
        rng = np.stack(erp_to_yin_yang(np.asarray(depths[v])[..., None], height=h, nearest=True))[..., 0]
        for g, kind in enumerate(edit.grids):
            d = geo.grid_directions(kind, h, w)
            p = geo.world_to_camera(d * rng[g][..., None] @ c2ws[v][:3, :3].T + c2ws[v][:3, 3], c2ws[1 - v])
            yang = ~geo.in_grid_domain("yin", p)
            (cy, ry), (cg, rg) = geo.project_to_grid("yin", p, h, w), geo.project_to_grid("yang", p, h, w)
            out[v, g, ..., 0], out[v, g, ..., 1], out[v, g, ..., 2] = yang, np.where(yang, cg, cy), np.where(yang, rg, ry)
            out[v, g, ..., 3], out[v, g, ..., 4] = 1.0, np.where(rng[g] > 0, 0, 2)
    return out


def weighted_iou(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray) -> float:
    h = pred.shape[0]
    wt = np.cos((np.arange(h) + 0.5) / h * np.pi - np.pi / 2)[:, None] * valid
    union = ((pred | gt) * wt).sum()
    return float(((pred & gt) * wt).sum() / union) if union else 1.0


def flow_baseline(img_a: np.ndarray, img_b: np.ndarray):
    """Dense DIS flow B -> A on grey ERPs: returns a function carrying an A mask to B."""
    import cv2

    grey = lambda im: cv2.cvtColor(np.ascontiguousarray((im * 255).astype(np.uint8)), cv2.COLOR_RGB2GRAY)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    flow = dis.calc(grey(img_b), grey(img_a), None)
    h, w = flow.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w]
    c = np.mod(np.rint(xx + flow[..., 0]).astype(np.int64), w)
    r = np.clip(np.rint(yy + flow[..., 1]).astype(np.int64), 0, h - 1)
    return lambda mask_a: mask_a[r, c]


def figure(path: Path, index, sel, prompt, scene, refs, target, gaussians) -> Path:
    """Prompt on A, mask A, mask B, target view after remove and after recolor (one PNG)."""
    from PIL import Image, ImageDraw

    from rasterizer.edit.ops import edit_gaussians
    from rasterizer.render import render

    tiles = []
    for v in range(2):
        im = (index.colour[v] * 255).astype(np.uint8)
        m = sel.masks[v]
        im[m] = (0.45 * im[m] + 0.55 * np.array([255, 40, 40])).astype(np.uint8)
        tiles.append(Image.fromarray(im))
    d = ImageDraw.Draw(tiles[0])
    for u, v in prompt:
        x, y = u * tiles[0].width, v * tiles[0].height
        d.ellipse([x - 7, y - 7, x + 7, y + 7], outline=(255, 255, 0), width=3)
    pose = scene.frames[target].c2w
    w = index.colour.shape[2]
    for op, kw in (("remove", {}), ("recolor", {"color": (0.1, 0.8, 0.2)})):
        g = edit_gaussians(gaussians, sel.gaussians, op, **kw)
        out = render(g, pose, width=w, normalize=True)
        tiles.append(Image.fromarray((np.clip(out.colour, 0, 1) * 255).astype(np.uint8)))
    labels = ["prompt + mask, reference A (00)", "carried mask, reference B (02)",
              f"target {target} after remove", f"target {target} after recolor"]
    tw, th = tiles[0].size
    canvas = Image.new("RGB", (2 * tw, 2 * (th + 18)), (255, 255, 255))
    for k, (t, lab) in enumerate(zip(tiles, labels)):
        x, y = (k % 2) * tw, (k // 2) * (th + 18)
        ImageDraw.Draw(canvas).text((x + 4, y + 2), lab, fill=(0, 0, 0))
        canvas.paste(t, (x, y + 18))
    canvas = canvas.resize((canvas.width // 2, canvas.height // 2))
    path.parent.mkdir(parents=True, exist_ok=True)
    canvas.save(path)
    return path


def run(model: Path, data: Path, threads: int = 2, out: Path = DEFAULT_OUT) -> dict:
    from rasterizer.edit import correspondences as corr
    from rasterizer.edit.scene import build_index, select_points
    from service.encoder import OnnxEncoder
    from service.pipeline import PipelineOptions, build_scene

    scene = load_scene(data)
    split = scene.splits[0]
    ra, rb = (scene.frames[n] for n in split.references)
    target = split.targets[0]
    encoder = OnnxEncoder(model, threads=threads)
    t0 = time.perf_counter()
    build = build_scene(encoder, ra.image(), rb.image(), ra.c2w, rb.c2w, PipelineOptions.from_dict({}))
    t_build = time.perf_counter() - t0
    t0 = time.perf_counter()
    blob = build.edit.to_bytes()
    t_pack = time.perf_counter() - t0
    t0 = time.perf_counter()
    blob_z = build.edit.to_bytes(compress=True)
    t_pack_z = time.perf_counter() - t0
    raw = build.edit.matches.nbytes
    images = [ra.image(), rb.image()]
    stored = type(build.edit).from_bytes(blob)  # what the service selects on: float16 ranges, unpacked matches
    t0 = time.perf_counter()
    index = build_index(stored, images)
    t_index = time.perf_counter() - t0
    t0 = time.perf_counter()
    build_index(stored, images, labels=index.superpixel_labels())
    t_index_stored = time.perf_counter() - t0
    he = index.erp_height
    depth_a, depth_b = (np.asarray(f.depth(), dtype=np.float32) for f in (ra, rb))
    if depth_a.shape[0] != he:
        raise SystemExit(f"GT depth is {depth_a.shape}, the index works at {he} rows: resample first")
    to_a, visible = gt_carry(depth_b, depth_a, rb.c2w, ra.c2w)
    flow = flow_baseline(index.colour[0], index.colour[1])
    if build.edit.grids == ("yin", "yang"):  # oracle: the same carry through matches from the GT ranges
        oracle_b = corr.erp_matches(gt_matches(build.edit, (depth_a, depth_b), (ra.c2w, rb.c2w)), 1,
                                    build.edit.grids, he)
    else:
        oracle_b = None
    rows, seconds, chosen = [], [], None
    for name, pts in PROMPTS.items():
        t0 = time.perf_counter()
        sel = select_points(index, 0, pts)
        seconds.append(time.perf_counter() - t0)
        mask_a = sel.masks[0]
        gt_b = mask_a.ravel()[to_a]
        row = {"prompt": name, "points": pts, "coverage_a": sel.coverage()[0], "coverage_b": sel.coverage()[1],
               "num_gaussians": int(sel.gaussians.sum()), "seconds": seconds[-1],
               "iou_ours": weighted_iou(sel.masks[1], gt_b, visible),
               "iou_same_pixels": weighted_iou(mask_a, gt_b, visible),
               "iou_flow": weighted_iou(flow(mask_a), gt_b, visible),
               "iou_oracle_gt_depth": None if oracle_b is None else weighted_iou(corr.carry(mask_a, oracle_b)[0], gt_b, visible),
               "gt_empty": bool(not (gt_b & visible).any())}
        rows.append(row)
        _log(f"{name}: ours {row['iou_ours']:.3f}, same pixels {row['iou_same_pixels']:.3f}, "
             f"flow {row['iou_flow']:.3f}, coverage A {row['coverage_a']:.4f} B {row['coverage_b']:.4f}")
        if name == FIGURE_PROMPT:
            chosen = sel
    t0 = time.perf_counter()
    labels, sizes = index.segments()
    t_segments = time.perf_counter() - t0
    agree = (labels[1] == labels[0].ravel()[to_a])[visible].mean()
    matched = [corr.erp_matches(build.edit.matches, v, build.edit.grids, he).valid.mean() for v in range(2)]
    fig = figure(out / "edit.png", index, chosen, PROMPTS[FIGURE_PROMPT], scene, (ra, rb), target, build.gaussians)
    mean = lambda k: float(np.mean([r[k] for r in rows]))
    return {
        "machine": machine_line(machine_info()), "model": model.name, "scene": scene.name,
        "references": list(split.references), "target": target, "erp_height": he,
        "miou": {"ours": mean("iou_ours"), "same_pixels": mean("iou_same_pixels"), "flow_dis": mean("iou_flow"),
                 "oracle_gt_depth": None if oracle_b is None else mean("iou_oracle_gt_depth")},
        "prompts": rows,
        "seconds": {"scene_build": t_build, "pack_matches": t_pack, "pack_matches_compressed": t_pack_z, "index_first": t_index,
                    "index_with_stored_superpixels": t_index_stored, "selection_mean": float(np.mean(seconds)),
                    "selection_max": float(np.max(seconds)), "segments": t_segments},
        "storage": {"matches_raw_bytes": int(raw), "edit_artifact_bytes": len(blob),
                    "edit_artifact_bytes_compressed": len(blob_z), "num_gaussians": len(build.gaussians),
                    "gaussian_bytes": int(sum(getattr(build.gaussians, f).nbytes
                                              for f in ("means", "scales", "quats", "opacities", "sh")))},
        "matched_fraction": {"a": float(matched[0]), "b": float(matched[1])},
        "segments": {"count": int(sizes.size), "label_agreement_at_gt_matches": float(agree)},
        "figure": str(fig),
    }


def markdown(res: dict) -> str:
    s, st = res["seconds"], res["storage"]
    lines = [
        f"Scene {res['scene']}, references {' / '.join(res['references'])} (A / B), ERP {res['erp_height']} rows; "
        f"model `{res['model']}`. Machine: {res['machine']}.", "",
        "IoU in B against the pseudo GT (A's mask carried through the GT range maps; B pixels A does not see are "
        "void), cos-latitude weighted. Same A mask for every column. Oracle (not a method: a check of the "
        "carrying itself) = our pull through matches built from the GT ranges instead of the encoder's.", "",
        "| prompt | coverage A | coverage B | ours | same pixels | optical flow (DIS) | oracle: GT-depth matches |",
        "|---|---|---|---|---|---|---|"]
    fmt = lambda v: "-" if v is None else f"{v:.3f}"
    for r in res["prompts"]:
        lines.append(f"| {r['prompt']} | {r['coverage_a']:.4f} | {r['coverage_b']:.4f} | {r['iou_ours']:.3f} | "
                     f"{r['iou_same_pixels']:.3f} | {r['iou_flow']:.3f} | {fmt(r['iou_oracle_gt_depth'])} |")
    m = res["miou"]
    lines += [f"| **mIoU** | | | **{m['ours']:.3f}** | {m['same_pixels']:.3f} | {m['flow_dis']:.3f} | "
              f"{fmt(m['oracle_gt_depth'])} |", "",
              f"Seconds: scene build {s['scene_build']:.2f}, index first use {s['index_first']:.2f} "
              f"({s['index_with_stored_superpixels']:.2f} with stored superpixels), selection mean "
              f"{s['selection_mean']:.3f} / max {s['selection_max']:.3f}, automatic segments {s['segments']:.2f}. "
              f"Correspondences stored with every scene: `edit.npz` (packed matches, float16 ranges, provenance) "
              f"{st['edit_artifact_bytes'] / 1e6:.2f} MB written in {s['pack_matches']:.3f} s (zlib-compressed: "
              f"{st['edit_artifact_bytes_compressed'] / 1e6:.2f} MB in {s['pack_matches_compressed']:.2f} s), beside "
              f"{st['gaussian_bytes'] / 1e6:.1f} MB of Gaussians; the raw float32 matches are "
              f"{st['matches_raw_bytes'] / 1e6:.1f} MB. "
              "Matches passing the graph's left-right / occlusion check: "
              f"A {res['matched_fraction']['a']:.3f}, B {res['matched_fraction']['b']:.3f}. "
              f"Automatic segments: {res['segments']['count']}, same label at "
              f"{res['segments']['label_agreement_at_gt_matches']:.3f} of GT-matched B pixels.", "",
              f"![prompt, masks, remove and recolor]({Path(res['figure']).name})"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="omnisplat-bench edit", description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--model", type=Path, default=None, help="ONNX model (default: the shipped 512x1024 quality model)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--readme", type=Path, default=None, help="README to update (marked block 'edit')")
    args = ap.parse_args(argv)
    model = args.model
    if model is None:
        from export.config import PRESETS

        from .models import bench_model
        model = bench_model(512, 1024, PRESETS["quality"]["num_planes"], log=_log)
    res = run(Path(model), args.data, args.threads, args.out)
    write_json(args.out / "edit.json", res)
    md = markdown(res)
    (args.out / "edit.md").write_text("# Selection consistency (bench edit)\n\n" + md.replace("](edit.png)", "](edit.png)")
                                      + "\n")
    if args.readme is not None:
        start, end = readme_markers("edit")
        block = "\n".join([start, "", md.replace("](edit.png)", "](docs/bench/edit.png)"), "", end])
        if not update_readme(args.readme, block, "edit"):
            _log(f"{args.readme} has no edit markers; not updated")
    print(json.dumps(res["miou"]))
    return 0

"""``omnisplat-bench quality``: error against run time over scene folders.

For every scene split: decode the two references, reconstruct Gaussians with
each setting's ONNX model, render every target, and score PSNR, SSIM and
WS-PSNR (conventions section 6) with wall seconds per stage (decode,
encoder, Gaussian head, render). Writes ``quality.json``, ``quality.md`` and
``quality_psnr_vs_seconds.png`` into ``--out`` (default ``docs/bench``).

    omnisplat-bench quality --data ../shared/data/m3d_bedroom ../shared/data/zind_room09
    omnisplat-bench quality --data DIR --short          # CI smoke run: one scene, one small model
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
from PIL import Image

from bench import metrics
from rasterizer.geometry import grid_directions
from rasterizer.render import to_uint8
from rasterizer.rig import overlay_rig, rig_layer
from rasterizer.scene_folder import SceneFolder, Split, load_scene

from .baselines import copy_nearest
from .machine import machine_info, machine_line
from .models import DEFAULT_MODELS_DIR, bench_model
from .report import ablation_markdown, aggregate, markdown, plot, readme_block, update_readme, write_json
from .settings import Setting, full_grid, parse_setting, short_grid

DEFAULT_OUT = Path(__file__).resolve().parents[1] / "docs" / "bench"
#: A split whose targets lie farther than this many baselines from the reference segment is "extrapolation".
EXTRAPOLATION_RATIO = 0.5


def _log(msg: str) -> None:
    print(f"[bench quality] {msg}", file=sys.stderr, flush=True)


# -- scene handling -----------------------------------------------------------

def is_extrapolation(scene: SceneFolder, split: Split, index: int) -> bool:
    """True if the split says so, or a target is > EXTRAPOLATION_RATIO baselines off the reference segment."""
    meta = scene.meta.get("splits", [])
    if index < len(meta) and "extrapolation" in meta[index]:
        return bool(meta[index]["extrapolation"])
    a = scene.frames[split.references[0]].c2w[:3, 3]
    b = scene.frames[split.references[1]].c2w[:3, 3]
    ab = b - a
    base = float(np.linalg.norm(ab))
    for name in split.targets:
        p = scene.frames[name].c2w[:3, 3]
        t = np.clip((p - a) @ ab / max(base * base, 1e-12), 0.0, 1.0)
        if np.linalg.norm(p - (a + t * ab)) > EXTRAPOLATION_RATIO * base:
            return True
    return False


def resize_erp_box(image: np.ndarray, width: int) -> np.ndarray:
    """Area-resample an ERP image to ``width`` x ``width/2`` (identity when already that size)."""
    h, w = image.shape[:2]
    if w == width:
        return image
    pil = Image.fromarray(to_uint8(image))
    return np.asarray(pil.resize((width, width // 2), Image.Resampling.BOX), dtype=np.float32) / 255.0


def score(pred: np.ndarray, target: np.ndarray) -> dict:
    """SSIM and the real-capture figures (:func:`bench.metrics.real_capture_scores`: PSNR above the nadir cap,
    PSNR, WS-PSNR, sharpness, GMSD) of a prediction against the ground truth (ERP, clipped to [0, 1])."""
    pred = np.clip(np.nan_to_num(pred, nan=0.0), 0.0, 1.0)
    return {**metrics.real_capture_scores(pred, target), "ssim": metrics.ssim(pred, target)}


#: Bin edges of the per-split opacity histogram: unconfident surfels sit at 0.3-0.4, confident ones near 0.99.
OPACITY_BINS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0)


def opacity_shares(opacities: np.ndarray) -> list[float]:
    """Share of ``opacities`` (N,) in each :data:`OPACITY_BINS` bin (the last one includes 1.0); sums to 1."""
    counts, _ = np.histogram(np.asarray(opacities, dtype=np.float64), bins=OPACITY_BINS)
    return (counts / max(int(counts.sum()), 1)).tolist()


def copy_floor(refs: list[tuple[np.ndarray, np.ndarray]], c2w_target: np.ndarray, target: np.ndarray) -> dict:
    """The copy floor of conventions section 6 (nearest reference turned to the target, rotation only),
    scored as :func:`bench.metrics.real_capture_scores`."""
    h, w = target.shape[:2]
    return metrics.real_capture_scores(copy_nearest(refs, c2w_target, h, w), target)


# -- per-setting reconstruction ------------------------------------------------

class Runner:
    """Holds the encoders (one per model) and runs one setting on one split."""

    def __init__(self, models_dir: Path, threads: int, warmup: bool):
        self.models_dir = models_dir
        self.threads = threads
        self.warmup = warmup
        self._encoders: dict = {}
        self._warm: set = set()
        self.paths: dict = {}  # model key -> ONNX path, filled before the sweep
        self.last_info: dict = {}  # ``info`` of the last reconstruction (near plane for the API's render cull)

    def encoder(self, setting: Setting):
        from service.encoder import OnnxEncoder

        key = setting.model_key
        if key not in self._encoders:
            self._encoders.clear()  # keep one session in memory at a time
            h, w, planes, erp, ds = key
            path = self.paths.get(key) or bench_model(h, w, planes, erp, downscale=ds, models_dir=self.models_dir,
                                                       threads=self.threads, log=_log)
            self._encoders[key] = OnnxEncoder(path, threads=self.threads)
        return self._encoders[key]

    def gaussians(self, setting: Setting, refs: list[tuple[np.ndarray, np.ndarray]], depths) -> tuple:
        """(Gaussians, {stage: seconds}) for a model or oracle setting."""
        if setting.kind == "oracle":
            from rasterizer.depth_gaussians import gaussians_from_depth

            t0 = time.perf_counter()
            g = oracle_gaussians(gaussians_from_depth, refs, depths)
            return g, {"encoder": 0.0, "gaussian_head": time.perf_counter() - t0}
        enc = self.encoder(setting)
        (img_a, c2w_a), (img_b, c2w_b) = refs
        if setting.api:
            from service.pipeline import PipelineOptions, build_scene

            def reconstruct():
                return build_scene(enc, img_a, img_b, c2w_a, c2w_b, PipelineOptions.from_dict({}))
        else:
            def reconstruct():
                return enc.reconstruct(img_a, img_b, c2w_a, c2w_b)
        if self.warmup and setting.model_key not in self._warm:
            reconstruct()
            self._warm.add(setting.model_key)
        t0 = time.perf_counter()
        rec = reconstruct()
        wall = time.perf_counter() - t0
        self.last_info = dict(getattr(rec, "info", {}) or {})
        return rec.gaussians, encoder_stages(rec.timings, wall)


def encoder_stages(timings: dict, wall: float) -> dict:
    """Split the encoder's wall time into "encoder" and "gaussian_head" using its own timings.

    Timing keys naming the head (``head``, ``gaussian``) count as the head;
    the rest of the wall time (resampling, ONNX run, pose inputs) is "encoder".
    """
    head = sum(float(v) for k, v in (timings or {}).items()
               if isinstance(v, (int, float)) and ("head" in k.lower() or "gaussian" in k.lower()) and "total" not in k.lower())
    head = min(head, wall)
    return {"encoder": wall - head, "gaussian_head": head}


def oracle_gaussians(gaussians_from_depth, refs, depths):
    """GT-depth Gaussians through the service's Gaussian path at full confidence: the head's surfels
    (sigma ``scale_factor_confident``, opacity ``opacity_max``) on each reference's ERP grid, the
    view-dependent colour fit and the environment shell. GT pixels without depth take the largest
    depth of their panorama (they are holes in the scanned mesh: windows, far openings)."""
    from export.config import EncoderConfig
    from rasterizer.gaussians import Gaussians
    from rasterizer.shell import environment_shell
    from rasterizer.view_colour import fit_view_colour

    cfg = EncoderConfig()
    valid = [np.isfinite(d) & (d > 0) for d in depths]
    ranges = np.stack([np.where(ok, d, d[ok].max())[None] for d, ok in zip(depths, valid)])  # (2, 1, H, W)
    poses = np.stack([c2w for _, c2w in refs])
    parts = [gaussians_from_depth(img, r[0], c2w, surfels=True, scale_factor=cfg.scale_factor_confident,
                                  thickness=cfg.ray_scale_ratio, max_stretch=cfg.max_stretch,
                                  opacity=cfg.opacity_max) for (img, c2w), r in zip(refs, ranges)]
    g = Gaussians.concatenate(parts)
    shell = environment_shell(g, ranges, poses, ("erp",))
    return Gaussians.concatenate([fit_view_colour(g, ranges, poses, ("erp",)), shell])


#: How a render is composited: "plain" = front to back over black, no division (what 3DGS viewers
#: show); "va" = colour divided by accumulated alpha where alpha >= 1/255.
COMPOSITING = ("plain", "va")
COMPOSITING_LABEL = {"plain": "plain", "va": "V/A"}


def render_view(gaussians, c2w: np.ndarray, width: int, rasterizer: str, compositing: str = "plain",
                sweep_near: float | None = None):
    """(colour, alpha) of an ERP render with the given rasterizer and compositing.

    The Yin-Yang path returns V/A colour; its plain colour is that times alpha (the merged
    premultiplied colour). The direct path returns plain colour; its V/A is :func:`alpha_normalised`.
    ``sweep_near``: the scene's sweep near plane, to cull as the render API does (``service.scenes``).
    """
    from rasterizer.camera import DEFAULT_NEAR
    from rasterizer.render import render
    from service.scenes import NEAR_CULL_PER_SWEEP_NEAR

    kwargs = {}
    if sweep_near is not None and sweep_near > 0:
        kwargs["near"] = min(DEFAULT_NEAR, NEAR_CULL_PER_SWEEP_NEAR * float(sweep_near))
    out = render(gaussians, c2w, projection="erp", width=width, method=rasterizer, **kwargs)
    alpha = np.asarray(out.alpha)
    return composited(np.asarray(out.colour), alpha, rasterizer, compositing), alpha


def composited(colour: np.ndarray, alpha: np.ndarray, rasterizer: str, compositing: str) -> np.ndarray:
    """An ERP render's colour (as ``render(..., method=rasterizer)`` returns it) in the given compositing."""
    if compositing not in COMPOSITING:
        raise ValueError(f"compositing must be one of {COMPOSITING}, got {compositing!r}")
    if rasterizer == "yinyang" and compositing == "plain":
        return colour * alpha[..., None]
    if rasterizer == "direct" and compositing == "va":
        return alpha_normalised(colour, alpha)
    return colour


def alpha_normalised(colour: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """colour / alpha where alpha >= 1/255, else 0: what the Yin-Yang merge does, applied to a direct render."""
    ok = alpha[..., None] >= 1.0 / 255.0
    return np.where(ok, colour / np.maximum(alpha[..., None], 1.0 / 255.0), 0.0)


# -- the bench ---------------------------------------------------------------------

def run(scene_dirs: list[Path], settings: list[Setting], *, models_dir: Path, threads: int = 2,
        render_width: int | None = None, warmup: bool = False, max_splits: int | None = None,
        compositing: str = "plain") -> list[dict]:
    """Per-target records for every (setting, scene split, target)."""
    runner = Runner(models_dir, threads, warmup)
    # Build every model first: the whole sweep then uses one snapshot of the exporter's code.
    for key in dict.fromkeys(s.model_key for s in settings if s.kind == "model"):
        h, w, planes, erp, ds = key
        runner.paths[key] = bench_model(h, w, planes, erp, downscale=ds, models_dir=models_dir, threads=threads,
                                         log=_log)
    records: list[dict] = []
    scenes = [load_scene(d) for d in scene_dirs]
    for setting in settings:
        for scene in scenes:
            if setting.kind == "oracle" and not scene.has_depth:
                continue
            for si, split in enumerate(scene.splits[:max_splits]):
                extra = is_extrapolation(scene, split, si)
                group = f"{scene.name} (extrapolation)" if extra else scene.name
                t0 = time.perf_counter()
                refs = [(scene.frames[n].image(), scene.frames[n].c2w) for n in split.references]
                decode = time.perf_counter() - t0
                depths = [scene.frames[n].depth() for n in split.references] if setting.kind == "oracle" else None
                stages = {"encoder": 0.0, "gaussian_head": 0.0}
                g = None
                model_info = {}
                if setting.kind != "copy":
                    g, stages = runner.gaussians(setting, refs, depths)
                surfels = None
                if g is not None:  # the environment shell (the last info["shell"] of an API scene) is a backdrop
                    surfels = opacity_shares(g.opacities[:len(g) - int(runner.last_info.get("shell", 0))])
                if setting.kind == "model":
                    enc = runner.encoder(setting)
                    model_info = {"model_file": enc.path.name, "model_sha256": enc.metadata.get("sha256", "")[:16]}
                for name in split.targets:
                    frame = scene.frames[name]
                    gt = frame.image()
                    width = render_width or gt.shape[1]
                    gt = resize_erp_box(gt, width)
                    t0 = time.perf_counter()
                    alpha = layer = None
                    if setting.kind == "copy":
                        pred = copy_nearest(refs, frame.c2w, width // 2, width)
                    else:
                        near = runner.last_info.get("near") if setting.api else None
                        pred, alpha = render_view(g, frame.c2w, width, setting.rasterizer, compositing, near)
                        layer = rig_layer(*(resize_erp_box(img, width) for img, _ in refs)) if setting.rig else None
                        if layer is not None:  # camera-attached: the target camera's own ERP rays
                            pred = overlay_rig(pred, grid_directions("erp", width // 2, width), layer)
                    t_render = time.perf_counter() - t0
                    label = "" if setting.kind == "copy" else f", {COMPOSITING_LABEL[compositing]}"
                    rec = {"setting": setting.slug, "setting_name": setting.name + label, "scene": scene.name,
                           "compositing": compositing,
                           "split": si, "group": group, "extrapolation": extra, "target": name,
                           "references": list(split.references), "width": width,
                           "finite": bool(np.all(np.isfinite(pred))),
                           **score(pred, gt), "copy_floor": copy_floor(refs, frame.c2w, gt),
                           "seconds": {"decode": decode, **stages, "render": t_render}}
                    if setting.rig:
                        rec["rig_detected"] = layer is not None
                    if alpha is not None:
                        rec["mean_alpha"] = float(alpha.mean())
                        rec["alpha_ge_099"] = float((alpha >= 0.99).mean())
                    if alpha is not None and setting.rasterizer == "direct" and compositing == "plain":
                        rec["psnr_alpha_normalised"] = metrics.psnr(np.clip(alpha_normalised(pred, alpha), 0, 1), gt)
                    if g is not None:
                        rec["num_gaussians"] = len(g)
                        rec["opacity_shares"] = surfels
                    rec.update(model_info)
                    records.append(rec)
                    _log(f"{setting.name} | {group} {name}: above nadir {rec['psnr_above_nadir']:.2f} dB "
                         f"(copy floor {rec['copy_floor']['psnr_above_nadir']:.2f}), PSNR {rec['psnr']:.2f}, "
                         f"sharpness {rec['sharpness']:.2f}, GMSD {rec['gmsd']:.3f}, {sum(rec['seconds'].values()):.2f} s")
    return records


def ablation_tables(settings: list[Setting], summary: list[dict]) -> list[str]:
    """The paper's Table 3 (encoder x rasterizer) for every model point where all four cells ran."""
    points: dict[tuple, dict] = {}
    for s in settings:
        if s.kind == "model":
            cell = ("Yin-Yang encoder" if not s.erp_encoder else "ERP encoder",
                    "Yin-Yang rasterizer" if s.rasterizer == "yinyang" else "direct ERP rasterizer")
            points.setdefault((s.height, s.width, s.planes, s.downscale), {})[cell] = s.slug
    out = []
    for (h, w, planes, ds), cells in points.items():
        if len(cells) == 4:
            feats = "" if ds is None else f", features /{ds}"
            out.append(ablation_markdown(summary, cells, f"Paper Table 3 ablation ({h}x{w}, {planes} planes{feats}): "
                                                         "mean PSNR / SSIM over scenes"))
    return out


def targets_markdown(records: list[dict]) -> str:
    """Per-target table of the real-capture figures (conventions section 6) against the copy floor."""
    lines = ["Per target: PSNR above -75 deg latitude (headline) / full PSNR / WS-PSNR in dB, sharpness, GMSD, "
             "and the copy floor's PSNR above the nadir (margin = headline - floor).", "",
             "| setting | scene | target | above nadir | PSNR | WS-PSNR | sharpness | GMSD | copy floor | margin |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in records:
        if r["setting"] == "copy":
            continue
        floor = r["copy_floor"]["psnr_above_nadir"]
        lines.append(f"| {r['setting']} | {r['scene']} | {r['target']} | {r['psnr_above_nadir']:.2f} | {r['psnr']:.2f} "
                     f"| {r['ws_psnr']:.2f} | {r['sharpness']:.2f} | {r['gmsd']:.3f} | {floor:.2f} "
                     f"| {r['psnr_above_nadir'] - floor:+.2f} |")
    return "\n".join(lines) + "\n"


def opacity_markdown(records: list[dict]) -> str:
    """Per split (first target's record), the share of its surfels (environment shell left out) per opacity bin."""
    edges = OPACITY_BINS
    head = " | ".join(f"{a:.1f}-{b:.1f}" for a, b in zip(edges[:-1], edges[1:]))
    lines = ["Opacity of each split's surfels (the environment shell left out): share per bin, in percent.", "",
             f"| setting | scene | references | {head} |", "|---|---|---|" + "---|" * (len(edges) - 1)]
    seen = set()
    for r in records:
        key = (r["setting"], r["scene"], tuple(r["references"]))
        if "opacity_shares" not in r or key in seen:
            continue
        seen.add(key)
        cells = " | ".join(f"{100 * x:.0f}" for x in r["opacity_shares"])
        lines.append(f"| {r['setting']} | {r['scene']} | {'+'.join(r['references'])} | {cells} |")
    return "\n".join(lines) + "\n"


def code_version() -> dict:
    """Git HEAD (read-only query) and whether the tree had local changes, plus the exporter source hash."""
    import subprocess

    from .models import REPO_ROOT, export_code_hash

    def git(*args):
        try:
            return subprocess.run(["git", *args], cwd=REPO_ROOT, capture_output=True, text=True, timeout=10).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return ""

    return {"git_head": git("rev-parse", "--short", "HEAD"), "uncommitted_changes": bool(git("status", "--porcelain")),
            "export_code_hash": export_code_hash()}


NOTES = [
    "Per-scene mean over targets, then the unweighted mean over scenes; splits whose targets lie more than "
    f"{EXTRAPOLATION_RATIO} baselines off the reference segment (zind_room09 refs pano_4+pano_5) are extrapolation, "
    "reported separately and kept out of the mean.",
    "Seconds are wall clock per novel view: decode = reading the two reference PNGs; encoder = "
    "`OnnxEncoder.reconstruct` minus its Gaussian stage (resampling, sweep inputs, the ONNX run, which also "
    "holds the pixel-aligned Gaussian head's maths); Gaussian head = the encoder's own `gaussians` timing "
    "(building the Gaussians from the graph outputs), for the oracle building the GT-depth Gaussians; "
    "render = one ERP render at the evaluation width. Reconstruction stages are shared by the targets of a "
    "split; no warm-up run (ONNX first-run overhead is included).",
    "Timings are wall clock on a 2-core machine and noisy, more so the higher the load average above; "
    "compare settings, not absolute numbers.",
    "Compositing is named beside every setting: plain = front to back over black with no division by alpha "
    "(what 3DGS viewers show; for the Yin-Yang rasterizer its V/A colour times alpha, i.e. the merged "
    "premultiplied colour), V/A = colour divided by accumulated alpha (`--compositing va`). A plain run's "
    "JSON also gives the direct render divided by its alpha (same render, no extra time).",
    f"PSNR above nadir = PSNR over the rows more than {metrics.NADIR_CAP_DEG:g} deg above the nadir: real captures "
    "show the camera-attached capture rig there (every zind_room09 panorama: a tripod disc below about -77 deg), "
    "which no reconstruction of the scene shows and copying a reference gets for free. A diagnostic beside PSNR, "
    "not instead.",
    "capture rig layer = the same render with the rig both references show at their nadir composited at the "
    "target camera's nadir (the render API's `rig=true`, not its default: it is camera-attached, so no 3DGS "
    "viewer shows it; rasterizer.rig). Scenes whose references show no common rig (m3d_bedroom) render as plain.",
    "copy nearest reference = the nearest reference rotated into the target's orientation (depth at infinity). "
    "GT-depth oracle = the ground-truth depth of both references through the service's Gaussian path at full "
    "confidence: the head's surfels, view-dependent colour and environment shell (scenes with depth only, so "
    "its mean covers m3d_bedroom alone).",
    "Generated by `omnisplat-bench quality`; do not edit by hand.",
]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="omnisplat-bench quality", description=__doc__.split("\n\n")[0])
    p.add_argument("--data", nargs="+", required=True, type=Path, help="scene folders (conventions section 2)")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output folder (default docs/bench)")
    p.add_argument("--models-dir", type=Path, default=DEFAULT_MODELS_DIR, help="ONNX model cache")
    p.add_argument("--setting", action="append", default=None,
                   help="run only these settings: 'HxW:planes[:yy|erp][:yinyang|direct]', 'oracle', 'copy' (repeatable)")
    p.add_argument("--short", action="store_true", help="smoke run: first scene, first split, one 64x128/16-plane model")
    p.add_argument("--render-width", type=int, default=None, help="evaluation width (default: the target image's)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--warmup", action="store_true", help="one untimed reconstruction per model before timing")
    p.add_argument("--compositing", choices=COMPOSITING, default="plain",
                   help="plain: front to back over black, no division (default, what viewers show); "
                        "va: colour divided by alpha")
    p.add_argument("--name", default="quality", help="output file stem (default 'quality')")
    p.add_argument("--readme", type=Path, default=None,
                   help="also replace the marked quality block of this README (e.g. README.md) with the mean table")
    args = p.parse_args(argv)

    missing = [d for d in args.data if not (d / "scene.json").exists()]
    if missing:
        p.error(f"not a scene folder (no scene.json): {', '.join(map(str, missing))}")
    if args.setting:
        settings = [parse_setting(s) for s in args.setting]
    else:
        settings = short_grid() if args.short else full_grid()
    data = args.data[:1] if args.short else args.data
    width = args.render_width or (256 if args.short else None)
    info = machine_info()
    t0 = time.perf_counter()
    records = run(data, settings, models_dir=args.models_dir, threads=args.threads, render_width=width,
                  warmup=args.warmup, max_splits=1 if args.short else None, compositing=args.compositing)
    summary = aggregate(records)
    line = machine_line(info)
    code = code_version()
    models = sorted({r["model_file"] for r in records if "model_file" in r})
    notes = NOTES + [f"Code: git {code['git_head']}{' + uncommitted changes' if code['uncommitted_changes'] else ''}; "
                     f"models: {', '.join(models) or 'none'} (the suffix hashes the exporter source; "
                     "a run that mixes suffixes mixes encoder versions)."]
    notes += [f"Command: `omnisplat-bench quality {' '.join(argv if argv is not None else sys.argv[1:])}`; "
                     f"total bench wall time {time.perf_counter() - t0:.0f} s."]
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / f"{args.name}.json", {"machine": info, "code": code, "notes": notes,
                                                 "settings": [s.to_dict() for s in settings],
                                                 "summary": summary, "records": records})
    md = markdown(summary, line, notes) + f"\n![PSNR against seconds]({args.name}_psnr_vs_seconds.png)\n"
    md += "".join("\n" + t for t in ablation_tables(settings, summary))
    md += "\n" + targets_markdown(records)
    md += "\n" + opacity_markdown(records)
    (args.out / f"{args.name}.md").write_text(md)
    plot(summary, args.out / f"{args.name}_psnr_vs_seconds.png", line)
    _log(f"wrote {args.out / (args.name + '.md')}")
    if args.readme is not None:
        rel = os.path.relpath(args.out, args.readme.resolve().parent)
        block = readme_block(md, line, f"{rel}/{args.name}_psnr_vs_seconds.png", f"{rel}/{args.name}.md")
        if not update_readme(args.readme, block):
            _log(f"{args.readme} has no quality markers; left unchanged")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

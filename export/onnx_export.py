"""Export the training-free encoder to ONNX (``omnisplat export``).

One static-shape model per (input size, plane count, setting): the
pose-dependent inputs are computed in numpy by :mod:`rasterizer.sweep` and
fed at run time, so the graph holds no matrix inverse, no atan2 and no
data-dependent shape. Settings and defaults go into ``metadata_props``;
:class:`service.encoder.OnnxEncoder` reads them back.
"""

from __future__ import annotations

import argparse
import json
import warnings
from pathlib import Path

import numpy as np
import onnx
import torch

from rasterizer.sweep import ERP_PAD, INPUT_NAMES, OUTPUT_NAMES

from .config import PRESETS, EncoderConfig, make_config
from .model import OmniSplatEncoder

OPSET = 18


def dummy_inputs(cfg: EncoderConfig) -> tuple[torch.Tensor, ...]:
    """Inputs of the right shapes and plausible values (a 1 m z-baseline pair)."""
    from rasterizer.sweep import sweep_inputs

    rng = np.random.default_rng(0)
    erp = lambda: torch.from_numpy(rng.random((1, 3, cfg.height, cfg.width), dtype=np.float32))
    c2w_b = np.eye(4)
    c2w_b[2, 3] = 1.0
    si = sweep_inputs(np.eye(4), c2w_b, near=cfg.near_per_baseline, far=cfg.far_per_baseline,
                      num_planes=cfg.num_planes, feature_size=cfg.feature_size, erp_encoder=cfg.erp_encoder)
    return (erp(), erp()) + tuple(torch.from_numpy(si[k]) for k in INPUT_NAMES[2:])


def metadata(cfg: EncoderConfig) -> dict[str, str]:
    """String metadata_props written into the model."""
    g = len(cfg.grids)
    h, w = cfg.feature_size
    return {
        "name": cfg.name,
        "version": cfg.version,
        "input_height": str(cfg.height),
        "input_width": str(cfg.width),
        "num_planes": str(cfg.num_planes),
        "grids": ",".join(cfg.grids),
        "erp_encoder": str(cfg.erp_encoder).lower(),
        "feature_height": str(h),
        "feature_width": str(w),
        "gaussian_grid_height": str(cfg.full_size[0]),
        "gaussian_grid_width": str(cfg.full_size[1]),
        "num_gaussians": str(cfg.num_gaussians),
        "near_per_baseline": repr(cfg.near_per_baseline),
        "far_per_baseline": repr(cfg.far_per_baseline),
        "erp_pad": str(ERP_PAD),
        "inputs": json.dumps({
            "erp_a": [1, 3, cfg.height, cfg.width], "erp_b": [1, 3, cfg.height, cfg.width],
            "warp_grids": [2, g, cfg.num_planes, h, w, 2], "rel_rt": [2, 3, 4],
            "inv_depths": [cfg.num_planes], "c2w": [2, 4, 4], "cam_quats": [2, 4]}),
        "outputs": ",".join(OUTPUT_NAMES),
        "settings": json.dumps(cfg.to_dict(), sort_keys=True),
    }


def export_model(out_path, *, height: int = 512, width: int = 1024, num_planes: int | None = None,
                 erp_encoder: bool = False, preset: str | None = "quality", downscale: int | None = None,
                 dynamo: bool = False, check: bool = True, **settings) -> Path:
    """Build the encoder for one input size / setting and write it to ``out_path``.

    ``preset`` ("fast" | "quality") picks plane count and feature resolution;
    explicit ``num_planes`` / ``downscale`` / other :class:`EncoderConfig`
    fields override it. Returns the path. ``check`` runs ``onnx.checker``.
    """
    cfg = make_config(preset, height=height, width=width, num_planes=num_planes,
                      erp_encoder=erp_encoder, downscale=downscale, **settings)
    model = OmniSplatEncoder(cfg).eval()
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            model, dummy_inputs(cfg), str(out_path), input_names=list(INPUT_NAMES),
            output_names=list(OUTPUT_NAMES), opset_version=OPSET, dynamo=dynamo,
            do_constant_folding=True,
        )
    proto = onnx.load(str(out_path))
    del proto.metadata_props[:]
    for key, value in metadata(cfg).items():
        proto.metadata_props.add(key=key, value=value)
    onnx.save(proto, str(out_path))  # inline weights: ~18 MB of per-pixel constants (rays, quats, grids)
    for extra in out_path.parent.glob(out_path.name + ".data"):
        extra.unlink()
    if check:
        onnx.checker.check_model(str(out_path))
    return out_path


def main(argv: list[str] | None = None) -> int:
    """``omnisplat export OUT.onnx [--height 512] [--preset fast|quality] ...``."""
    p = argparse.ArgumentParser(prog="omnisplat export", description=__doc__.splitlines()[0])
    p.add_argument("out", type=Path, help="output .onnx path")
    p.add_argument("--height", type=int, default=512, help="ERP input height (width = 2 x height)")
    p.add_argument("--preset", choices=sorted(PRESETS), default="quality")
    p.add_argument("--num-planes", type=int, default=None)
    p.add_argument("--downscale", type=int, default=None, help="feature grid = Gaussian grid / downscale")
    p.add_argument("--erp-encoder", action="store_true", help="ablation: sweep on the raw ERP, no Yin-Yang")
    args = p.parse_args(argv)
    path = export_model(args.out, height=args.height, width=2 * args.height, num_planes=args.num_planes,
                        erp_encoder=args.erp_encoder, preset=args.preset, downscale=args.downscale)
    meta = {p.key: p.value for p in onnx.load(str(path), load_external_data=False).metadata_props}
    print(json.dumps({"path": str(path), "bytes": path.stat().st_size,
                      **{k: meta[k] for k in ("name", "num_planes", "grids", "num_gaussians")}}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""ONNX models for bench settings: built once with ``export.onnx_export.export_model``, cached on disk.

Export runs in a child Python process so the bench process itself never
imports torch (``service/`` stays torch-free, docs/conventions.md section 7).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

from service.model_files import export_code_hash

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_MODELS_DIR = Path(os.environ.get("OMNISPLAT_BENCH_MODELS", Path.home() / ".cache" / "omnisplat" / "bench"))

_EXPORT_SNIPPET = """
import json, sys
import torch
torch.set_num_threads({threads})
from export.onnx_export import export_model
kw = json.loads(sys.argv[1])
out = kw.pop("out_path")
print(export_model(out, **kw))
"""


class ModelBuildError(RuntimeError):
    """Exporting a bench model failed; the message carries the exporter's stderr tail."""


def model_filename(height: int, width: int, planes: int, erp_encoder: bool, downscale: int | None = None,
                   layout: bool = True) -> str:
    ds = "" if downscale is None else f"_d{downscale}"
    lay = "" if layout else "_nolayout"
    return f"omnisplat_{height}x{width}_p{planes}_{'erp' if erp_encoder else 'yy'}{ds}{lay}_{export_code_hash()}.onnx"


def bench_model(height: int, width: int, planes: int, erp_encoder: bool = False, *, downscale: int | None = None,
                 layout: bool = True, models_dir: Path | str = DEFAULT_MODELS_DIR, threads: int = 2,
                 timeout_s: float = 1800.0, log=None) -> Path:
    """Path of the cached model for these settings, exporting it first if missing.

    ``downscale`` (feature grid = Gaussian grid / downscale) defaults to the exporter's preset;
    ``layout=False`` builds it without the layout prior (export/layout.py; an ablation).
    """
    models_dir = Path(models_dir)
    models_dir.mkdir(parents=True, exist_ok=True)
    path = models_dir / model_filename(height, width, planes, erp_encoder, downscale, layout)
    if path.exists() and path.stat().st_size > 0:
        return path
    kwargs = {"out_path": str(path), "height": height, "width": width, "num_planes": planes, "erp_encoder": erp_encoder}
    if downscale is not None:
        kwargs["downscale"] = int(downscale)
    if not layout:
        kwargs["layout_strength"] = 0.0
        kwargs["floor_clamp"] = False
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO_ROOT), os.environ.get("PYTHONPATH", "")])}
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", _EXPORT_SNIPPET.format(threads=int(threads)), json.dumps(kwargs)],
                          cwd=REPO_ROOT, env=env, capture_output=True, text=True, timeout=timeout_s)
    if proc.returncode != 0 or not path.exists():
        raise ModelBuildError(f"export of {path.name} failed (rc {proc.returncode}):\n{proc.stderr[-3000:]}")
    if log:
        log(f"exported {path.name} in {time.perf_counter() - t0:.1f} s")
    return path

"""Small labelled image strips (PIL only) for bench case figures."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from rasterizer.render import to_uint8


def _to_uint8(img: np.ndarray) -> np.ndarray:
    img = np.asarray(img, dtype=np.float32)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    return to_uint8(np.nan_to_num(img, nan=1.0))  # NaN shows white


def strip(panels: list[tuple[str, np.ndarray | None]], path: Path, caption: str = "", panel_width: int = 224) -> Path:
    """Save panels side by side (each resized to ``panel_width`` x W/2) with titles and a caption.

    A ``None`` panel is drawn grey (e.g. no render because the input was refused).
    """
    ph = panel_width // 2
    title_h, cap_lines = 14, textwrap.wrap(caption, width=max(40, panel_width * len(panels) // 6))[:4]
    gap = 6
    step = panel_width + gap
    canvas = Image.new("RGB", (step * len(panels) - gap, title_h + ph + 12 * len(cap_lines) + 4), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    for i, (title, img) in enumerate(panels):
        if img is None:
            tile = Image.new("RGB", (panel_width, ph), (160, 160, 160))
        else:
            tile = Image.fromarray(_to_uint8(img)).resize((panel_width, ph), Image.Resampling.BILINEAR)
        canvas.paste(tile, (i * step, title_h))
        draw.text((i * step + 3, 1), title[:40], fill=(0, 0, 0))
    for j, line in enumerate(cap_lines):
        draw.text((3, title_h + ph + 2 + 12 * j), line, fill=(0, 0, 0))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # A 128-colour palette keeps a committed figure to tens of kB; fine for a visual check.
    canvas.quantize(colors=128, method=Image.Quantize.MEDIANCUT).save(path, optimize=True)
    return path

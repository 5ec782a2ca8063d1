"""Aggregate per-target bench records and write the JSON, markdown table and plot.

Aggregation follows the evaluation protocol: mean over the targets of a
scene group, then the unweighted mean over scene groups. A group is a scene,
or ``<scene> (extrapolation)`` for splits whose targets lie outside the
reference segment; those are reported separately and kept out of the mean.
"""

from __future__ import annotations

import json
import math
from collections import defaultdict
from pathlib import Path

import numpy as np

METRICS = ("psnr", "ssim", "ws_psnr", "psnr_alpha_normalised")
STAGES = ("decode", "encoder", "gaussian_head", "render")


def _mean(values) -> float | None:
    vals = [v for v in values if v is not None and math.isfinite(v)]
    return float(np.mean(vals)) if vals else None


def aggregate(records: list[dict]) -> list[dict]:
    """One summary per setting (in first-seen order) from per-target records.

    A record has ``setting`` (slug), ``group``, ``extrapolation`` (bool), the
    metrics and ``seconds`` ({stage: s}). Returns dicts with ``per_group``
    (metric and stage means per group), ``mean`` (over non-extrapolation
    groups) and ``extrapolation`` (mean over extrapolation groups, or None).
    """
    by_setting: dict[str, list[dict]] = defaultdict(list)
    for r in records:
        by_setting[r["setting"]].append(r)
    out = []
    for slug, recs in by_setting.items():
        groups: dict[str, list[dict]] = defaultdict(list)
        for r in recs:
            groups[r["group"]].append(r)
        per_group = {}
        for g, rs in groups.items():
            entry = {m: _mean(r.get(m) for r in rs) for m in METRICS}
            entry["seconds"] = {s: _mean(r["seconds"].get(s) for r in rs) for s in STAGES}
            entry["seconds"]["total"] = _mean(sum(v for v in r["seconds"].values() if v is not None) for r in rs)
            entry["targets"] = len(rs)
            entry["extrapolation"] = bool(rs[0]["extrapolation"])
            per_group[g] = entry
        out.append({
            "setting": slug,
            "name": recs[0].get("setting_name", slug),
            "per_group": per_group,
            "mean": _mean_over(per_group, extrapolation=False),
            "extrapolation": _mean_over(per_group, extrapolation=True),
        })
    return out


def _mean_over(per_group: dict, *, extrapolation: bool) -> dict | None:
    groups = [v for v in per_group.values() if v["extrapolation"] == extrapolation]
    if not groups:
        return None
    res = {m: _mean(g[m] for g in groups) for m in METRICS}
    res["seconds"] = {s: _mean(g["seconds"][s] for g in groups) for s in (*STAGES, "total")}
    res["groups"] = len(groups)
    return res


def _fmt(v, digits=2) -> str:
    return "–" if v is None else f"{v:.{digits}f}"


def markdown(summary: list[dict], machine_line: str, notes: list[str], title: str = "Quality against run time") -> str:
    """The markdown report: machine, notes, the table, a per-group breakdown."""
    groups = []
    for s in summary:
        for g, v in s["per_group"].items():
            if g not in groups and not v["extrapolation"]:
                groups.append(g)
    extra_groups = []
    for s in summary:
        for g, v in s["per_group"].items():
            if g not in extra_groups and v["extrapolation"]:
                extra_groups.append(g)
    lines = [f"# {title}", "", f"Machine: {machine_line}", ""]
    lines += [f"- {n}" for n in notes]
    lines += ["", "## Mean over scenes (extrapolation splits excluded)", ""]
    head = ["setting", "PSNR", "SSIM", "WS-PSNR", "decode s", "encoder s", "head s", "render s", "total s"]
    head += [f"PSNR {g}" for g in groups] + [f"PSNR {g}" for g in extra_groups]
    lines.append("| " + " | ".join(head) + " |")
    lines.append("|" + "---|" * len(head))
    for s in summary:
        m = s["mean"] or {k: None for k in METRICS} | {"seconds": {}}
        sec = m["seconds"]
        row = [s["name"], _fmt(m["psnr"]), _fmt(m["ssim"], 4), _fmt(m["ws_psnr"])]
        row += [_fmt(sec.get(k), 3) for k in (*STAGES, "total")]
        row += [_fmt(s["per_group"].get(g, {}).get("psnr")) for g in groups + extra_groups]
        lines.append("| " + " | ".join(row) + " |")
    lines += ["", "## Per scene group", "", "| setting | group | targets | PSNR | SSIM | WS-PSNR | total s |", "|---|---|---|---|---|---|---|"]
    for s in summary:
        for g, v in s["per_group"].items():
            lines.append(f"| {s['name']} | {g} | {v['targets']} | {_fmt(v['psnr'])} | {_fmt(v['ssim'], 4)} | "
                         f"{_fmt(v['ws_psnr'])} | {_fmt(v['seconds']['total'], 3)} |")
    return "\n".join(lines) + "\n"


def ablation_markdown(summary: list[dict], cells: dict[tuple[str, str], str], title: str) -> str:
    """A rows x columns table of mean PSNR / SSIM; ``cells`` maps (row label, column label) -> setting slug."""
    by_slug = {s["setting"]: s for s in summary}
    rows = list(dict.fromkeys(r for r, _ in cells))
    cols = list(dict.fromkeys(c for _, c in cells))
    lines = [f"## {title}", "", "| | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]
    for r in rows:
        vals = []
        for c in cols:
            m = (by_slug.get(cells.get((r, c), "")) or {}).get("mean")
            if not m:
                vals.append("–")
                continue
            norm = m.get("psnr_alpha_normalised")
            vals.append(f"{_fmt(m['psnr'])} dB / {_fmt(m['ssim'], 4)}" +
                        ("" if norm is None else f" (colour / alpha: {_fmt(norm)} dB)"))
        lines.append(f"| {r} | " + " | ".join(vals) + " |")
    return "\n".join(lines) + "\n"


def _style(slug: str, index: int):
    """(marker, colour) of a setting: star oracle, square copy, circle YY encoder, triangle ERP encoder;
    hollow for the direct ERP rasterizer."""
    import matplotlib

    marker = "*" if slug.startswith("oracle") else "s" if slug == "copy" else "^" if "erpenc" in slug else "o"
    colour = "tab:green" if slug.startswith("oracle") else "0.4" if slug == "copy" else \
        matplotlib.colormaps["tab10"](index % 10)
    return marker, colour


def plot(summary: list[dict], path: Path, machine_line: str) -> Path:
    """PSNR against wall seconds per novel view, one point per setting.

    Panels: the mean over scenes (settings that cover every scene), then one per scene group
    (the oracle appears where the scene has GT depth).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups: list[str] = []
    for s in summary:
        groups += [g for g in s["per_group"] if g not in groups]
    n_interp = max((s["mean"] or {}).get("groups", 0) for s in summary) if summary else 0
    panels = [("mean over scenes (extrapolation excluded)", None)] + [(g, g) for g in groups]
    cols = 2
    rows = (len(panels) + 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(12, 4.2 * rows + 1.6), dpi=100, squeeze=False)
    handles = {}
    for ax, (title, group) in zip(axes.flat, panels):
        for i, s in enumerate(summary):
            if group is None:
                m = s["mean"]
                if not m or m.get("groups", 0) < n_interp:
                    continue  # e.g. the oracle, which covers only scenes with GT depth
            else:
                m = s["per_group"].get(group)
            if not m or m["psnr"] is None or not m["seconds"].get("total"):
                continue
            marker, colour = _style(s["setting"], i)
            hollow = "direct" in s["setting"]
            h = ax.scatter(m["seconds"]["total"], m["psnr"], marker=marker, s=110 if marker == "*" else 60,
                           facecolors="none" if hollow else colour, edgecolors=colour, linewidths=1.6, zorder=3)
            handles.setdefault(s["name"], h)
        ax.set_xscale("log")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("wall s per novel view (decode + encoder + head + render)", fontsize=8)
        ax.set_ylabel("PSNR (dB)", fontsize=8)
        ax.grid(True, which="both", alpha=0.3)
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    fig.legend(list(handles.values()), list(handles.keys()), loc="lower center", ncol=2, fontsize=7.5, frameon=False)
    fig.suptitle("omnisplat: error against run time (hollow = direct ERP rasterizer, triangle = ERP encoder)",
                 fontsize=11)
    fig.text(0.01, 0.005, machine_line[:200], fontsize=6, color="0.35")
    legend_rows = (len(handles) + 1) // 2
    fig.tight_layout(rect=(0, min(0.45, 0.022 * legend_rows + 0.03), 1, 0.97))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def write_json(path: Path, payload: dict) -> Path:
    """Write ``payload`` as indented JSON (NaN/Inf become null)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(_clean(payload), indent=1) + "\n")
    return path


def _clean(obj):
    if isinstance(obj, dict):
        return {k: _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj

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

METRICS = ("psnr", "ssim", "ws_psnr")
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
            entry = {m: _mean(r[m] for r in rs) for m in METRICS}
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
        m = s["mean"] or {m: None for m in METRICS} | {"seconds": {}}
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


def plot(summary: list[dict], path: Path, machine_line: str) -> Path:
    """PSNR (mean over scenes) against total seconds per novel view, one point per setting."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 5.5), dpi=110)
    for s in summary:
        m = s["mean"]
        if not m or m["psnr"] is None or not m["seconds"].get("total"):
            continue
        slug = s["setting"]
        marker = "*" if slug.startswith("oracle") else ("s" if slug == "copy" else ("o" if "yyenc" in slug else "^"))
        colour = "tab:green" if slug.startswith("oracle") else ("tab:grey" if slug == "copy" else
                                                               ("tab:blue" if slug.startswith("256x") else "tab:red"))
        if "direct" in slug:
            colour = "tab:orange" if "yyenc" in slug else "tab:purple"
        ax.scatter(m["seconds"]["total"], m["psnr"], marker=marker, s=80, color=colour, zorder=3)
        ax.annotate(s["name"], (m["seconds"]["total"], m["psnr"]), fontsize=6.5, xytext=(4, 3), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_xlabel("wall seconds per novel view (decode + encoder + Gaussian head + render), log scale")
    ax.set_ylabel("PSNR (dB), mean over scenes")
    ax.set_title("omnisplat: error against run time", fontsize=11)
    ax.grid(True, which="both", alpha=0.3)
    fig.text(0.01, 0.01, machine_line[:180], fontsize=5.5, color="0.35")
    fig.tight_layout(rect=(0, 0.03, 1, 1))
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

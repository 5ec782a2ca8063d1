"""The compaction driver: run the enabled steps in order and assemble the output in layout order."""

from __future__ import annotations

import time
from dataclasses import dataclass, fields, replace

import numpy as np

from ..gaussians import Gaussians
from ..shell import shell_layout
from .merge import SmoothMerge, smooth_merge_blocks
from .options import CompactionError, CompactionOptions, count_limit
from .provenance import Provenance
from .steps import cap_keep_mask


@dataclass(frozen=True)
class CompactionResult:
    """What :func:`compact_result` returns.

    gaussians: the output (kept inputs and merged blocks, in layout order);
    provenance: its layout positions (a merged block's is its top-left
    pixel); block: (M,) side of the pixel block each output Gaussian stands
    for (1 = an input kept as it is); index: input indices of the inputs kept
    as they are (ascending); stats: see :func:`compact`.
    """

    gaussians: Gaussians
    provenance: Provenance
    block: np.ndarray
    index: np.ndarray
    stats: dict


def _interleave(gaussians: Gaussians, index: np.ndarray, pos: np.ndarray, merged: SmoothMerge | None,
                tail: Gaussians | None = None):
    """Kept inputs ``gaussians[index]`` (layout positions ``pos``) and the merged blocks (if any), in layout
    order, then the ``tail`` Gaussians (in the returned Gaussians only, not in the positions or blocks).

    The same as concatenating them and a stable argsort by position (without merged blocks: the kept
    inputs in their order); when both position lists are already ascending (the usual case) each output
    row is written once, at its place. SH bands a part lacks are zero.
    """
    m_pos = np.zeros(0, np.int64) if merged is None else merged.index
    if merged is not None and not (np.all(pos[1:] > pos[:-1]) and np.all(m_pos[1:] > m_pos[:-1])):
        out_g = Gaussians.concatenate([gaussians.subset(index), merged.gaussians])
        out_pos = np.concatenate([pos, m_pos])
        out_block = np.concatenate([np.ones(index.size, dtype=np.int64), merged.block])
        order = np.argsort(out_pos, kind="stable")
        out_g = out_g.subset(order)
        return (out_g if tail is None else Gaussians.concatenate([out_g, tail])), out_pos[order], out_block[order]
    total = index.size + m_pos.size
    m_slot = np.searchsorted(pos, m_pos, side="right") + np.arange(m_pos.size)  # inputs first on equal positions
    is_m = np.zeros(total, dtype=bool)
    is_m[m_slot] = True
    in_slot = np.flatnonzero(~is_m) if m_pos.size else slice(0, total)
    rows = total + (0 if tail is None else len(tail))
    pieces = [(gaussians, in_slot, index)]  # (part, its output rows, its rows taken from the part or None: all)
    if merged is not None:
        pieces.append((merged.gaussians, m_slot, None))
    if tail is not None:
        pieces.append((tail, slice(total, rows), None))
    k = max(part.sh.shape[1] for part, _, _ in pieces)
    cols = []
    for f in fields(Gaussians):
        out = np.empty((rows,) + ((k, 3) if f.name == "sh" else getattr(gaussians, f.name).shape[1:]), dtype=np.float32)
        for part, at, take in pieces:
            src = getattr(part, f.name)
            if take is not None:
                src = np.take(src, take, axis=0)
            if f.name == "sh" and src.shape[1] < k:
                out[at, :src.shape[1]] = src
                out[at, src.shape[1]:] = 0.0
            else:
                out[at] = src
        cols.append(out)
    out_pos = np.empty(total, dtype=np.int64)
    out_pos[in_slot] = pos
    out_pos[m_slot] = m_pos
    out_block = np.ones(total, dtype=np.int64)
    if merged is not None:
        out_block[m_slot] = merged.block
    return Gaussians(*cols), out_pos, out_block


def compact_result(gaussians: Gaussians, provenance: Provenance, options: CompactionOptions | None = None, *,
                   confidence: np.ndarray | None = None) -> CompactionResult:
    """Run the enabled steps in order (see the module docstring)."""
    opts = options or CompactionOptions()
    if provenance.shell:
        return _compact_with_shell(gaussians, provenance, opts, confidence)
    return _compact_layout(gaussians, provenance, opts, confidence)


def _compact_layout(gaussians: Gaussians, provenance: Provenance, opts: CompactionOptions, confidence: np.ndarray | None,
                    tail: Gaussians | None = None) -> CompactionResult:
    """:func:`compact_result` of pixel-aligned Gaussians. ``tail``: Gaussians written after the output in the
    same arrays (the shell; then its gaussians have more rows than its provenance and blocks), only
    without a count cap."""
    n = len(gaussians)
    flat = provenance.flat_index(n)  # validates the count
    alive = np.ones(n, dtype=bool)
    removed: dict[str, int] = {}
    seconds: dict[str, float] = {}

    def step(name: str, keep: np.ndarray | None, t0: float) -> None:
        before = int(alive.sum())
        if keep is not None:
            alive[:] &= keep
        removed[name] = before - int(alive.sum())
        seconds[name] = round(time.perf_counter() - t0, 4)

    t0 = time.perf_counter()
    keep = gaussians.opacities >= np.float32(opts.min_opacity) if opts.min_opacity > 0 else None
    if opts.min_confidence > 0:
        if confidence is None:
            raise CompactionError("min_confidence needs per-Gaussian confidence")
        conf = np.asarray(confidence, dtype=np.float32).reshape(-1)
        if conf.size == provenance.full_count and conf.size != n:
            conf = conf[flat]
        if conf.shape != (n,):
            raise CompactionError(f"confidence has {conf.size} values for {n} Gaussians")
        sure = conf >= np.float32(opts.min_confidence)
        keep = sure if keep is None else keep & sure
    step("min_opacity", keep, t0)

    t0 = time.perf_counter()
    smooth_stats = {"merged": 0, "added": 0, "blocks": {}}
    merged = None
    limit = count_limit(opts, gaussians.sh.shape[1])
    if opts.merge_smooth:
        excess = None if limit is None else int(alive.sum()) - limit  # merge before the cap drops
        sm = smooth_merge_blocks(gaussians, provenance, alive, levels=opts.smooth_levels,
                                 colour_tol=opts.smooth_colour_tol, opacity_tol=opts.smooth_opacity_tol,
                                 plane_tol=opts.smooth_plane_tol, max_incidence_deg=opts.smooth_max_incidence_deg,
                                 budget=excess if excess is not None and excess > 0 else None)
        alive &= ~sm.drop
        merged = sm
        smooth_stats = {"merged": int(sm.drop.sum()), "added": len(sm.gaussians),
                        "blocks": {str(k): v for k, v in sm.blocks.items()}}
    removed["merge_smooth"] = smooth_stats["merged"] - smooth_stats["added"]
    seconds["merge_smooth"] = round(time.perf_counter() - t0, 4)

    t0 = time.perf_counter()
    index = np.flatnonzero(alive)
    out_pos = flat[index]
    out_g, out_pos, out_block = _interleave(gaussians, index, out_pos,
                                            merged if merged is not None and len(merged.gaussians) else None, tail)
    out_prov = Provenance(provenance.grids, provenance.height, provenance.width, provenance.c2w, out_pos)
    seconds["assemble"] = round(time.perf_counter() - t0, 4)

    t0 = time.perf_counter()
    if limit is not None and tail is not None:
        raise CompactionError("a tail is appended only without a count cap")
    removed["cap"] = 0
    if limit is not None and limit < len(out_g):
        kept = np.flatnonzero(cap_keep_mask(out_g, out_prov, np.ones(len(out_g), bool), limit))
        removed["cap"] = len(out_g) - kept.size
        kept_inputs = out_block[kept] == 1
        index = index[np.isin(flat[index], out_pos[kept][kept_inputs])]
        out_g, out_pos, out_block = out_g.subset(kept), out_pos[kept], out_block[kept]
        out_prov = Provenance(provenance.grids, provenance.height, provenance.width, provenance.c2w, out_pos)
    seconds["cap"] = round(time.perf_counter() - t0, 4)

    stats = {"input": n, "output": out_block.size, "removed": removed, "merge_smooth": smooth_stats,
             "seconds": seconds, "options": opts.to_dict()}
    return CompactionResult(out_g, out_prov, out_block, index, stats)


def _compact_with_shell(gaussians: Gaussians, provenance: Provenance, opts: CompactionOptions,
                        confidence: np.ndarray | None) -> CompactionResult:
    """Compact the pixel-aligned Gaussians; the shell after them is appended unchanged (its blocks'
    top-left pixels as provenance, :func:`rasterizer.shell.shell_layout`)."""
    n, count = len(gaussians), provenance.shell
    if n < count:
        raise CompactionError(f"{n} Gaussians but a shell of {count}")
    index, block = shell_layout(provenance.views, len(provenance.grids), provenance.height, provenance.width)
    if index.size != count:
        raise CompactionError(f"shell of {count} Gaussians, layout {index.size}")
    shell = gaussians.subset(slice(n - count, n))  # views: no copy of the layout
    keep = shell.opacities >= np.float32(opts.min_opacity) if opts.min_opacity > 0 else np.ones(count, bool)
    limit = count_limit(opts, gaussians.sh.shape[1])
    front_opts = opts
    capped = 0
    widen = 1.0
    if limit is not None:  # the cap counts the shell too; a cap below the shell's size thins it evenly
        kept = np.flatnonzero(keep)
        if kept.size > limit:
            thin = np.zeros(count, bool)
            thin[kept[np.linspace(0, kept.size - 1, limit).astype(np.int64)]] = True
            capped, keep = kept.size - int(thin.sum()), thin
            widen = float(np.sqrt(kept.size / max(limit, 1)))
        front_opts = replace(opts, max_count=limit - int(keep.sum()), max_bytes=None)
    kept_shell = shell if keep.all() else shell.subset(keep)
    if widen > 1.0:  # each disc kept stands for the ones dropped around it: its side grows with their spacing
        kept_shell = replace(kept_shell, scales=kept_shell.scales * np.float32(widen))
    front = gaussians.subset(slice(0, n - count))
    if limit is None:  # the shell written into the output's arrays with it
        res = _compact_layout(front, replace(provenance, shell=0), front_opts, confidence, tail=kept_shell)
        out_g = res.gaussians
    else:
        res = _compact_layout(front, replace(provenance, shell=0), front_opts, confidence)
        out_g = Gaussians.concatenate([res.gaussians, kept_shell])
    pos = np.concatenate([res.provenance.flat_index(res.block.size), index[keep]])
    removed = dict(res.stats["removed"])
    removed["min_opacity"] += int(count - capped - keep.sum())
    removed["cap"] += capped
    stats = {**res.stats, "input": n, "output": len(out_g), "removed": removed, "shell": int(keep.sum()),
             "options": opts.to_dict()}
    return CompactionResult(out_g, Provenance(provenance.grids, provenance.height, provenance.width, provenance.c2w, pos),
                            np.concatenate([res.block, block[keep]]), res.index, stats)


def compact_index(gaussians: Gaussians, provenance: Provenance, options: CompactionOptions | None = None, *,
                  confidence: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Indices (ascending) of the inputs kept as they are, and the stats dict (see :func:`compact`).

    Without ``merge_smooth`` these are exactly the output; with it the merged
    blocks come in addition (:func:`compact_result` has both).
    """
    res = compact_result(gaussians, provenance, options, confidence=confidence)
    return res.index, res.stats


def compact(gaussians: Gaussians, provenance: Provenance, options: CompactionOptions | None = None, *,
            confidence: np.ndarray | None = None) -> tuple[Gaussians, dict]:
    """The Gaussians a scene needs, and how many each step removed.

    Returns (Gaussians in layout order, stats) with stats = ``{"input": N,
    "output": M, "removed": {"min_opacity", "merge_smooth", "cap"}: counts (merge_smooth: inputs
    merged minus merged Gaussians added, so the counts sum to N - M),
    "merge_smooth": {"merged", "added", "blocks": {side: count}}, "seconds":
    per step (and "assemble", building the output), "options": ...}``. Without ``merge_smooth`` the output is a
    subset of the input in its original order.
    """
    res = compact_result(gaussians, provenance, options, confidence=confidence)
    return res.gaussians, res.stats

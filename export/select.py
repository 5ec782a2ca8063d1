"""Element selection for the exported graph: ``torch.where`` as mask arithmetic.

onnxruntime's CPU ``Where`` takes about ten times a ``Mul`` of the same size (1.9 ms against 0.17 ms on a
(2, 2, 256, 768) float32 plane, two intra-op threads), so the graph selects with ``a * m + b * (1 - m)``,
m the condition as 0 / 1. That equals ``torch.where`` for finite a and b (up to the sign of a zero); an
infinite or NaN value in the branch not taken would leak through, so callers pass finite values only.
"""

from __future__ import annotations

import torch


def select_many(cond: torch.Tensor, a: tuple, b: tuple) -> tuple[torch.Tensor, ...]:
    """``torch.where(cond, a[i], b[i])`` for each pair of finite tensors or numbers (one mask for all)."""
    dtype = next(x.dtype for x in (*a, *b) if isinstance(x, torch.Tensor))
    m = cond.to(dtype)
    n = 1.0 - m
    return tuple(x * m + y * n for x, y in zip(a, b))


def select(cond: torch.Tensor, a, b) -> torch.Tensor:
    """``torch.where(cond, a, b)`` for finite tensors or numbers a and b."""
    return select_many(cond, (a,), (b,))[0]

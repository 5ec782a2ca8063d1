"""Where each Gaussian of a reconstruction came from: view, grid, row, column (and the shell after them)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .options import CompactionError


@dataclass(frozen=True)
class Provenance:
    """Where each Gaussian came from: grid layout [view][grid][row][col] plus poses.

    grids: grid kinds per view, e.g. ("yin", "yang") or ("erp",); height,
    width: size of one grid; c2w: (V, 4, 4) reference poses; index: (N,)
    flat position of each Gaussian in the full layout, or None when the
    Gaussians are the full layout in order; shell: how many Gaussians after
    those are the environment shell (:mod:`rasterizer.shell`), which
    compaction passes through unchanged.
    """

    grids: tuple[str, ...]
    height: int
    width: int
    c2w: np.ndarray
    index: np.ndarray | None = None
    shell: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "c2w", np.asarray(self.c2w, dtype=np.float64).reshape(-1, 4, 4))
        if self.index is not None:
            object.__setattr__(self, "index", np.asarray(self.index, dtype=np.int64))

    @classmethod
    def from_reconstruction(cls, reconstruction, c2w_a, c2w_b) -> "Provenance":
        """Layout of an :class:`service.encoder.Reconstruction` (range_maps (2, G, H, W))."""
        v, g, h, w = np.shape(reconstruction.range_maps)
        grids = ("erp",) if g == 1 else ("yin", "yang")
        shell = int(getattr(reconstruction, "shell", 0))
        prov = cls(grids, h, w, np.stack([np.asarray(c2w_a), np.asarray(c2w_b)]), shell=shell)
        if len(reconstruction.gaussians) != prov.full_count + shell:
            raise CompactionError(
                f"reconstruction has {len(reconstruction.gaussians)} Gaussians, layout {prov.full_count} "
                f"+ shell {shell}: run the encoder without min_opacity and compact with "
                "CompactionOptions.min_opacity instead")
        return prov

    @property
    def views(self) -> int:
        return int(self.c2w.shape[0])

    @property
    def full_count(self) -> int:
        return self.views * len(self.grids) * self.height * self.width

    def flat_index(self, n: int) -> np.ndarray:
        """(n,) flat layout positions of ``n`` Gaussians (checks the count)."""
        if self.index is None:
            if n != self.full_count:
                raise CompactionError(f"{n} Gaussians but the layout has {self.full_count}")
            return np.arange(n, dtype=np.int64)
        if self.index.shape != (n,):
            raise CompactionError(f"provenance index has shape {self.index.shape}, expected ({n},)")
        return self.index

    def decode(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(view, grid, row, col) int arrays of ``n`` Gaussians."""
        flat = self.flat_index(n)
        per_grid = self.height * self.width
        vg, pix = np.divmod(flat, per_grid)
        view, grid = np.divmod(vg, len(self.grids))
        row, col = np.divmod(pix, self.width)
        return view, grid, row, col

    def subset(self, keep: np.ndarray, n: int) -> "Provenance":
        """Provenance of ``gaussians.subset(keep)`` (of the pixel-aligned ones: no shell)."""
        return Provenance(self.grids, self.height, self.width, self.c2w, self.flat_index(n)[keep])

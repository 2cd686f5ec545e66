"""A sampled grid of f: the common input of the mesh extractions (``core.dual``, marching cubes)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Grid:
    """f at the nodes ``origin + index * cell`` (unit frame).

    ``values`` (nx+1, ny+1, nz+1): exact where the surface may pass (every corner of every cell
    it crosses), interpolated with the right sign elsewhere; positive on the boundary, so that its
    zero level set is closed. ``evaluated``: how many nodes were evaluated.
    """

    values: np.ndarray
    origin: np.ndarray
    cell: float
    evaluated: int = 0

    def position(self, index: np.ndarray) -> np.ndarray:
        """Unit-frame positions (n, 3) of fractional grid indices (n, 3)."""
        return self.origin + np.asarray(index, dtype=np.float64) * self.cell

    def values_off_zero(self) -> np.ndarray:
        """``values`` as float32, those within 0.001 cells of zero moved to ±0.001 cells.

        Keeps every crossing of the zero level off the grid's nodes, where marching cubes would
        put two vertices of a triangle on one point (a face of no area, which touches its
        neighbours) and where a crossing's grid edge, and so dual contouring's quad, would be
        ambiguous; each crossing then lies at least ~0.0006 cells from a node (float32 resolves
        0.00002 at 160 cells)."""
        tiny = np.float32(1e-3 * self.cell)
        values = self.values.astype(np.float32)
        return np.where(np.abs(values) < tiny, np.where(values < 0, -tiny, tiny), values)

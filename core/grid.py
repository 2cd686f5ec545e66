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

"""Where the fit looks besides the input points: eikonal samples, and what is known of empty space."""

from __future__ import annotations

import numpy as np
import torch
from scipy import ndimage
from scipy.spatial import cKDTree
from torch import Tensor

# The shape fills [-0.5, 0.5]^3 in the unit frame; uniform samples cover a slightly larger box.
BOX_HALF_SIZE = 0.6


def local_scales(points: np.ndarray, neighbour: int = 50) -> np.ndarray:
    """Per-point distance to the ``neighbour``-th nearest input point (IGR's local noise scale)."""
    k = min(neighbour, len(points) - 1)
    distances, _ = cKDTree(points).query(points, k=k + 1)
    return distances[:, -1]


def eikonal_samples(batch: Tensor, scales: Tensor, n_uniform: int, generator: torch.Generator) -> Tensor:
    """The batch points moved by Gaussian noise of their local scale, then ``n_uniform`` points
    drawn uniformly in the box (last)."""
    near = batch + torch.randn(batch.shape, generator=generator, dtype=batch.dtype) * scales[:, None]
    box = (torch.rand((n_uniform, 3), generator=generator, dtype=batch.dtype) * 2 - 1) * BOX_HALF_SIZE
    return torch.cat([near, box])


def draw_batch(cloud: Tensor, scales: Tensor, size: int, generator: torch.Generator) -> tuple[Tensor, Tensor]:
    """One step's inputs: ``size`` input points drawn at random, and their eikonal samples (near
    the first half of them, then ``size // 8`` uniform in the box)."""
    index = torch.randint(len(cloud), (size,), generator=generator)
    near = index[: max(size // 2, 1)]
    return cloud[index], eikonal_samples(cloud[near], scales[near], max(size // 8, 1), generator)


class FreeSpace:
    """What the cloud says about empty space, for the free-space term.

    ``distance`` is the distance from a sample to the nearest input point: a surface through the
    points is at least that far away, give or take ``margin`` (noise and sampling gaps). Where it
    can, ``sign`` also tells inside (-1) from outside (+1): the input points are voxelised, the
    voxels dilated by one so that the sampling gaps close, and the empty voxels that cannot be
    reached from the box's boundary are inside. Near the points (the dilated voxels) and for
    clouds that do not enclose a volume, the sign is unknown (0).
    """

    def __init__(self, points: np.ndarray):
        self.tree = cKDTree(points)
        spacing = self.tree.query(points, k=5)[0]
        self.margin = float(2 * np.median(spacing[:, 1]))
        self.voxel = float(np.median(spacing[:, 4]))
        cells = int(np.ceil(2 * BOX_HALF_SIZE / self.voxel))
        shell = np.zeros((cells,) * 3, dtype=bool)
        index = np.clip(((points + BOX_HALF_SIZE) / self.voxel).astype(int), 0, cells - 1)
        shell[tuple(index.T)] = True
        shell = ndimage.binary_dilation(shell, structure=np.ones((3, 3, 3), dtype=bool))
        enclosed = ndimage.binary_fill_holes(shell)
        sign = np.where(enclosed, 0, 1).astype(np.int8)
        sign[enclosed & ~shell] = -1
        self.sign_grid = torch.as_tensor(sign)

    def distance_and_sign(self, samples: Tensor) -> tuple[Tensor, Tensor]:
        """The distance from each sample to the nearest input point, and its sign (-1, 0 or +1)."""
        distance = torch.as_tensor(self.tree.query(samples.numpy(), k=1)[0], dtype=samples.dtype)
        cells = self.sign_grid.shape[0]
        index = ((samples + BOX_HALF_SIZE) / self.voxel).long().clamp(0, cells - 1)
        sign = self.sign_grid[index[:, 0], index[:, 1], index[:, 2]].to(samples.dtype)
        return distance, sign

"""The loss terms: L = L_vanish + λ1·L_eikonal + λ2·L_laplacian (the paper's), + λ3·L_free_space
+ λ4·L_normal."""

from __future__ import annotations

import torch
from torch import Tensor


def vanish_loss(f_points: Tensor) -> Tensor:
    """Mean |f| over the input points: the surface passes through them."""
    return f_points.abs().mean()


def eikonal_loss(grad: Tensor) -> Tensor:
    """Mean (‖∇f‖ - 1)² over the samples: f is a distance function."""
    return (grad.norm(dim=1) - 1).square().mean()


def normal_loss(grad_points: Tensor, normals: Tensor, outward: Tensor, edges: Tensor) -> Tensor:
    """Mean 1 - cos of the angle between ∇f and the cloud's own normal at the input points off the
    edges (``edges``: DES's mask, or empty to keep every point); where the normal's orientation is
    unknown (``outward`` False), 1 - |cos|, either way along it.

    ``normals`` (n, 3) come from ``core.sampling.plane_normals``, oriented where the free-space map
    tells (``FreeSpace.outward``). Without this term nothing tells a plug from a hole: a thin plate's
    small hole filled with solid costs the vanish term a little at the points of its wall, which
    then lie inside, and meets every other term; but f's gradient there runs along the hole's axis,
    across the wall's normal. The orientation keeps the term from holding a surface the wrong way
    round (a pocket's floor with a thin void under it, facing down); the edge points are left out,
    as from the Laplacian term, since their planes average two faces.
    """
    cosine = (grad_points * normals).sum(dim=1) / grad_points.norm(dim=1).clamp_min(1e-12)
    keep = 1.0 - edges.to(cosine.dtype) if edges.numel() else torch.ones_like(cosine)
    return _mean_over(1 - torch.where(outward, cosine, cosine.abs()), keep)


def laplacian_loss(
    lap_points: Tensor,
    tau: float | Tensor,
    edge_sampling: bool,
    penalty: str = "quadratic",
    scale: float | Tensor = 1.0,
) -> tuple[Tensor, Tensor]:
    """Mean penalty of Δf over the non-edge points, and the edge mask (|Δf| >= tau) left out.

    With ``edge_sampling`` (DES) the mask is taken from the current Δf, so it is re-selected at
    every step, before the backward pass; without it every point counts and the mask is empty.
    ``penalty`` is the paper's ``"quadratic"`` (Δf)², or ``"robust"``: Geman-McClure,
    (Δf)² / (1 + (Δf / scale)²), which is (Δf)² for small values and levels off at scale², so
    that its pull fades for |Δf| beyond a few ``scale``. The quadratic pulls hardest on the points
    just below tau, at the border of every edge, and wears edges away from there.
    """
    edges = lap_points.detach().abs() >= tau if edge_sampling else torch.zeros_like(lap_points, dtype=torch.bool)
    square = lap_points.square()
    if penalty == "robust":
        square = square / (1 + square / scale**2)
    return _mean_over(square, 1.0 - edges.to(square.dtype)), edges


def _mean_over(values: Tensor, keep: Tensor) -> Tensor:
    """The mean of ``values`` (n,) over the rows where ``keep`` (n,) is 1, 0 where it is 0
    everywhere. Weights instead of a boolean index keep every shape fixed, so that a compiled
    step (``core.fit``) is one graph."""
    return (values * keep).sum() / keep.sum().clamp_min(1.0)


def free_space_loss(f_samples: Tensor, distance: Tensor, sign: Tensor, margin: float | Tensor) -> Tensor:
    """Mean hinge that keeps the surface out of empty space.

    A sample at ``distance`` from the nearest input point is at least ``distance - margin`` from
    the surface: |f| must be that large, with the right sign where ``sign`` is known (±1) and
    either sign where it is not (0). A spurious sheet, a filled hole or a lump left over from the
    initial sphere, far from every point, violates it; a surface through the points does not.
    """
    signed = torch.where(sign != 0, sign * f_samples, f_samples.abs())
    return torch.relu(distance - margin - signed).mean()

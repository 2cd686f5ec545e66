"""core.extract: coarse-to-fine marching cubes, normals and Laplacian at points, empty surfaces.

Three networks (width 64, depth 2, β = 100): a freshly initialised one (a lumpy sphere of radius
about 0.3), one with randomly perturbed weights (a blob that is no sphere) and one briefly fitted
to a box cloud from evaluation.shapes (flat faces, sharp edges). Torch runs on one thread here: on a
shared two-core machine, two OpenMP threads competing with another process run 10-50x slower.
"""

from __future__ import annotations

import copy
import functools

import numpy as np
import pytest
import torch

from core import extract
from core.errors import EmptySurfaceError
from core.extract import GRID_MARGIN, evaluate, extract_mesh, normals_and_laplacian, unit_normals
from core.network import ImplicitNetwork, derivatives_autograd

UNIT_LOW, UNIT_HIGH = np.full(3, -0.5), np.full(3, 0.5)
# The box given to extract_mesh per network: a brief fit leaves f barely positive at the unit box's
# margin, so its grid gets more room (the surface must not reach the grid's boundary).
BOXES = {"sphere": 0.5, "blob": 0.5, "fitted": 0.6}


pytestmark = pytest.mark.usefixtures("one_thread")


def _sphere() -> ImplicitNetwork:
    return ImplicitNetwork(64, 2, 100.0, radius=0.3, generator=torch.Generator().manual_seed(1))


def _blob() -> ImplicitNetwork:
    generator = torch.Generator().manual_seed(0)
    model = ImplicitNetwork(64, 2, 100.0, generator=generator)
    with torch.no_grad():
        for layer in model.layers[:-1]:
            layer.weight.add_(0.5 * layer.weight.std() * torch.randn(layer.weight.shape, generator=generator))
            layer.bias.add_(0.025 * torch.randn(layer.bias.shape, generator=generator))
    return model


def _fitted() -> ImplicitNetwork:
    from core import network as network_module
    from core.fit import fit
    from core.params import FitParams
    from evaluation.shapes import sample_shape

    cloud = sample_shape("box", n_points=3000, seed=0).points
    kernels = network_module._kernels
    compiled, kernels.compiled = kernels.compiled, False  # eager: no compile for the fit's shapes
    try:
        params = FitParams(
            iterations=300, width=64, depth=2, batch_points=512, learning_rate=5e-3, final_learning_rate=2.5e-4, seed=0
        )
        return fit(cloud, params)
    finally:
        kernels.compiled = compiled


_MAKERS = {"sphere": _sphere, "blob": _blob, "fitted": _fitted}


@functools.cache
def network(name: str) -> ImplicitNetwork:
    model = _MAKERS[name]()
    model.requires_grad_(False)
    return model


def box(name: str) -> tuple[np.ndarray, np.ndarray]:
    return np.full(3, -BOXES[name]), np.full(3, BOXES[name])


@functools.cache
def mesh_of(name: str, resolution: int):
    return extract_mesh(network(name), resolution, *box(name))


def dense_mesh(name, resolution, monkeypatch):
    """The same extraction with every cell marked as near the surface: f at every grid node."""
    with monkeypatch.context() as patch:
        every_cell = lambda values, *spacing: np.ones(np.subtract(values.shape, 1), bool)  # noqa: E731
        patch.setattr(extract, "_near_cells", every_cell)
        patch.setattr(extract, "_sign_change_cells", every_cell)
        return extract_mesh(network(name), resolution, *box(name))


def f_at(model, points: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return model(torch.as_tensor(points, dtype=torch.float32)).numpy()


def box_points(n=100_000, seed=0, half=0.5 + GRID_MARGIN):
    return np.random.default_rng(seed).uniform(-half, half, (n, 3))


@pytest.mark.parametrize("name", ["sphere", "blob", "fitted"])
def test_networks_are_usable_fixtures(name):
    """Preconditions: a closed zero level set strictly inside the grid box, and no sphere for blob/fitted."""
    model = network(name)
    half = BOXES[name] + GRID_MARGIN
    faces = box_points(20_000, seed=1, half=half)
    faces[np.arange(len(faces)), np.arange(len(faces)) % 3] = np.where(np.arange(len(faces)) % 2, half, -half)
    assert (f_at(model, faces) > 0).all(), "f must be positive on the grid box's boundary"
    assert f_at(model, np.zeros((1, 3)))[0] < 0
    if name != "sphere":
        mesh, _ = mesh_of(name, 64)
        radii = np.linalg.norm(mesh.vertices - mesh.vertices.mean(axis=0), axis=1)
        assert radii.max() > 1.4 * radii.min(), "the surface should not be a sphere"


@pytest.mark.parametrize("name, resolution", [("sphere", 128), ("blob", 96), ("fitted", 128), ("fitted", 64)])
def test_coarse_to_fine_equals_dense(name, resolution, monkeypatch):
    mesh, stats = mesh_of(name, resolution)
    dense, dense_stats = dense_mesh(name, resolution, monkeypatch)
    assert stats["grid_nodes"] == dense_stats["grid_nodes"]
    assert dense_stats["evaluated_nodes"] >= dense_stats["grid_nodes"]
    assert len(mesh.vertices) == len(dense.vertices) > 1000
    np.testing.assert_allclose(mesh.vertices, dense.vertices, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(mesh.faces, dense.faces)


@pytest.mark.parametrize("name", ["sphere", "blob", "fitted"])
def test_mesh_is_closed_and_on_the_zero_level(name):
    mesh, _ = mesh_of(name, 96)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert len(mesh.split(only_watertight=False)) == 1
    # Marching cubes interpolates f linearly along cell edges: the vertices lie on f = 0 to within
    # a small fraction of a cell (the cell is 1.1 / 96 ≈ 0.011 here).
    values = np.abs(f_at(network(name), mesh.vertices))
    assert values.max() < 0.1 * (1 + 2 * GRID_MARGIN) / 96
    low, high = box(name)
    assert (mesh.bounds[0] >= low - GRID_MARGIN).all() and (mesh.bounds[1] <= high + GRID_MARGIN).all()


@pytest.mark.parametrize("name", ["sphere", "blob", "fitted"])
def test_mesh_is_oriented_outward(name):
    model = network(name)
    mesh, _ = mesh_of(name, 96)
    # Its volume is that of {f < 0}, estimated by Monte Carlo in the grid box.
    half = BOXES[name] + GRID_MARGIN
    inside = (f_at(model, box_points(half=half)) < 0).mean() * (2 * half) ** 3
    assert mesh.volume == pytest.approx(inside, rel=0.05)
    _, grad, _ = model.derivatives(torch.as_tensor(mesh.triangles_center, dtype=torch.float32), laplacian_rows=0)
    agreement = (mesh.face_normals * torch.nn.functional.normalize(grad, dim=1).numpy()).sum(axis=1)
    assert np.median(agreement) > 0.95


def test_mesh_volume_magnitude_matches_inside():
    """The part of the orientation check that holds today: |volume| is the volume of {f < 0}."""
    mesh, _ = mesh_of("blob", 96)
    inside = (f_at(network("blob"), box_points()) < 0).mean() * (1 + 2 * GRID_MARGIN) ** 3
    assert abs(mesh.volume) == pytest.approx(inside, rel=0.05)


@pytest.mark.parametrize("name, share", [("sphere", 0.12), ("fitted", 0.15)])
def test_evaluates_far_fewer_nodes_than_dense(name, share):
    mesh, stats = mesh_of(name, 256)
    # ``resolution`` cells span the unit extent plus its two margins
    assert stats["grid_nodes"] >= (256 * (2 * BOXES[name] + 2 * GRID_MARGIN) / (1 + 2 * GRID_MARGIN)) ** 3
    assert stats["evaluated_nodes"] < share * stats["grid_nodes"]
    assert mesh.is_watertight


def test_normals_and_laplacian_match_the_network():
    model = network("blob")
    mesh, _ = mesh_of("blob", 64)
    points = np.concatenate([mesh.vertices[::7], box_points(500, seed=2)])
    normals, laplacian = normals_and_laplacian(model, points)
    assert normals.shape == (len(points), 3) and laplacian.shape == (len(points),)
    _, grad, lap = derivatives_autograd(copy.deepcopy(model).double(), torch.as_tensor(points, dtype=torch.float64))
    expected = torch.nn.functional.normalize(grad, dim=1).detach().numpy()
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    np.testing.assert_allclose(normals, expected, atol=1e-4)
    lap = lap.detach().numpy()
    assert np.abs(lap).max() > 1.0  # a real Laplacian, not zeros
    np.testing.assert_allclose(laplacian, lap, atol=1e-4 * np.abs(lap).max())


def test_unit_normals_without_the_laplacian_are_the_same_normals():
    model = network("blob")
    points = box_points(3000, seed=4)
    normals, _ = normals_and_laplacian(model, points)
    alone = unit_normals(model, points, chunk=501)
    assert alone.shape == (len(points), 3) and alone.dtype == np.float32
    np.testing.assert_allclose(alone, normals, rtol=0, atol=1e-6)


def test_normals_point_outward_on_a_sphere():
    model = network("sphere")
    mesh, _ = mesh_of("sphere", 64)
    points = mesh.vertices[::5]
    normals, _ = normals_and_laplacian(model, points)
    radial = points / np.linalg.norm(points, axis=1, keepdims=True)
    cosine = (normals * radial).sum(axis=1)
    assert cosine.min() > 0.3 and np.median(cosine) > 0.9
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)


@pytest.mark.parametrize("shift", [+10.0, -10.0])
def test_no_zero_level_set_raises(shift):
    model = _sphere()
    with torch.no_grad():
        model.layers[-1].bias += shift
    values = f_at(model, box_points(10_000))
    assert (np.sign(values) == np.sign(shift)).all()
    with pytest.raises(EmptySurfaceError, match="no zero level set"):
        extract_mesh(model, 64, UNIT_LOW, UNIT_HIGH)


def test_tiny_box_still_meshes_a_surface_inside():
    """A cloud's box smaller than the unit cube gets a proportionally smaller grid, same cell size."""
    low, high = np.array([-0.5, -0.5, -0.1]), np.array([0.5, 0.5, 0.1])
    model = network("sphere")
    with pytest.raises(EmptySurfaceError):
        extract_mesh(model, 64, np.full(3, -0.02), np.full(3, 0.02))  # inside the sphere: f < 0 throughout
    mesh, stats = extract_mesh(model, 64, low, high)
    assert stats["grid_nodes"] < 0.5 * mesh_of("sphere", 64)[1]["grid_nodes"]
    assert mesh.bounds[1][2] <= 0.1 + GRID_MARGIN + 2 * (1 + 2 * GRID_MARGIN) / 64  # rounded to coarse cells


def test_chunking_gives_identical_results(monkeypatch):
    model = network("blob")
    points = box_points(5000, seed=3)
    normals, laplacian = normals_and_laplacian(model, points)
    normals_small, laplacian_small = normals_and_laplacian(model, points, chunk=37)
    np.testing.assert_allclose(normals_small, normals, rtol=0, atol=1e-6)
    np.testing.assert_allclose(laplacian_small, laplacian, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(evaluate(model, points, chunk=333), evaluate(model, points), rtol=0, atol=1e-6)

    mesh, stats = mesh_of("blob", 96)
    monkeypatch.setattr(extract, "evaluate", functools.partial(evaluate, chunk=1000))
    chunked, chunked_stats = extract_mesh(model, 96, UNIT_LOW, UNIT_HIGH)
    assert chunked_stats == stats
    np.testing.assert_allclose(chunked.vertices, mesh.vertices, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(chunked.faces, mesh.faces)


# --- a non-manifold dual contour ------------------------------------------------------------------


def test_closed_manifold_means_two_faces_on_every_edge():
    import trimesh

    cube = trimesh.creation.box()
    assert extract.is_closed_manifold(cube)
    assert not extract.is_closed_manifold(trimesh.Trimesh(cube.vertices, cube.faces[1:], process=False))
    # Two cubes sharing one edge, welded there: that edge has four faces.
    other = cube.copy()
    other.apply_translation([1.0, 1.0, 0.0])
    welded = trimesh.util.concatenate([cube, other])
    welded.merge_vertices()
    assert welded.is_volume is False and not extract.is_closed_manifold(welded)
    assert not extract.is_closed_manifold(trimesh.Trimesh())


def _with_an_edge_of_four_faces(mesh):
    """``mesh`` with two faces glued onto one of its edges (a fin): that edge then has four faces."""
    import trimesh

    a, b = mesh.faces[0][:2]
    tip = len(mesh.vertices)
    vertices = np.vstack([mesh.vertices, mesh.vertices[[a, b]].mean(axis=0) + 0.01])
    return trimesh.Trimesh(vertices, np.vstack([mesh.faces, [[a, b, tip], [b, a, tip]]]), process=False)


def test_a_non_manifold_dual_contour_is_extracted_again_one_cell_finer(monkeypatch):
    real_contour, real_grid = extract.dual_contour, extract.sample_grid
    resolutions = []

    def recorded_grid(values_at, resolution, *args):
        resolutions.append(resolution)
        return real_grid(values_at, resolution, *args)

    def first_one_non_manifold(*args):
        mesh = real_contour(*args)
        return _with_an_edge_of_four_faces(mesh) if len(resolutions) == 1 else mesh

    monkeypatch.setattr(extract, "sample_grid", recorded_grid)
    monkeypatch.setattr(extract, "dual_contour", first_one_non_manifold)
    mesh, _ = extract_mesh(network("sphere"), 48, *box("sphere"), method="sharp")
    assert resolutions == [48, 49]
    assert mesh.is_watertight and extract.is_closed_manifold(mesh) and mesh.volume > 0


def test_after_every_grid_non_manifold_the_mesh_is_marching_cubes(monkeypatch):
    real = extract.dual_contour
    monkeypatch.setattr(extract, "dual_contour", lambda *args: _with_an_edge_of_four_faces(real(*args)))
    mesh, _ = extract_mesh(network("sphere"), 48, *box("sphere"), method="sharp")
    marching, _ = extract_mesh(network("sphere"), 48 + extract.DUAL_ATTEMPTS - 1, *box("sphere"), method="mc")
    assert mesh.is_watertight and np.array_equal(mesh.faces, marching.faces)
    assert np.allclose(mesh.vertices, marching.vertices)


# --- specks --------------------------------------------------------------------------------------


def test_parts_smaller_than_a_few_cells_are_dropped_lumps_and_voids_alike():
    """A sphere of radius 0.3 with, 2 cells wide, a lump beside it and a void inside it (faces
    turned in), and a part of radius 2.5 cells (65 cells³) that stays: the specks go, every
    other face and vertex stays as it was, in order."""
    import trimesh

    cell = 0.01
    body = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    lump = trimesh.creation.icosphere(subdivisions=1, radius=cell)
    lump.apply_translation([0.5, 0, 0])
    void = trimesh.creation.icosphere(subdivisions=1, radius=cell)
    void.invert()
    kept = trimesh.creation.icosphere(subdivisions=2, radius=2.5 * cell)
    kept.apply_translation([0, 0.5, 0])
    parts = [body, lump, void, kept]
    mesh = trimesh.util.concatenate(parts)
    cleaned = extract.without_specks(mesh, cell)
    expected = trimesh.util.concatenate([body, kept])
    np.testing.assert_array_equal(cleaned.vertices, expected.vertices)
    np.testing.assert_array_equal(cleaned.faces, expected.faces)
    assert cleaned.is_watertight


def test_a_lone_speck_is_kept_as_the_largest_part():
    import trimesh

    speck = trimesh.creation.icosphere(subdivisions=1, radius=0.001)
    cleaned = extract.without_specks(speck, 0.01)
    assert len(cleaned.faces) == len(speck.faces)

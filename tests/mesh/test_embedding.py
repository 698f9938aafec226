"""Barycentric embedding of surface points in a tetrahedralised capsule (real fTetWild)."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse
import torch
import trimesh

from torchfit.mesh import (Embedding, MeshError, TetOptions, box_tetrahedra, boundary_faces,
                           embed_points, tetrahedralize)
from torchfit.mesh.embedding import dof_matrix
from torchfit.mesh.surface import surface_volume, surface_warnings

TOL = 1e-10


@pytest.fixture(scope="module")
def capsule(tmp_path_factory):
    """``(surface, tet points, tet cells)`` of a coarse capsule (about 400 tetrahedra)."""
    surface = trimesh.creation.capsule(height=0.58, radius=0.045, count=[8, 8])
    cache = tmp_path_factory.mktemp("tetcache")
    mesh = tetrahedralize(surface.vertices, surface.faces, TetOptions(edge_length_fac=0.1),
                          cache_dir=cache)
    return surface, mesh.points, mesh.cells


def inner_points(points, cells, n=300, seed=0):
    """Random points strictly inside random tetrahedra: ``(x, tet, weights)``."""
    rng = np.random.default_rng(seed)
    tets = rng.integers(len(cells), size=n)
    w = rng.uniform(0.05, 1.0, (n, 4))
    w /= w.sum(axis=1, keepdims=True)
    return np.einsum("nk,nkd->nd", w, points[cells[tets]]), tets, w


def test_boundary_faces_are_the_outward_hull_of_a_box():
    box = box_tetrahedra(2, 2, 2, size=(1.0, 2.0, 3.0))
    faces, owners = boundary_faces(box.cells)
    assert faces.shape == (6 * 4 * 2, 3) and owners.shape == (48,)
    # every boundary face is a face of its owner, and they close the box outward
    assert all(set(f) < set(box.cells[o]) for f, o in zip(faces.tolist(), owners.tolist()))
    surface = trimesh.Trimesh(box.points, faces, process=False)
    assert surface_warnings(trimesh.Trimesh(box.points[np.unique(faces)],
                                            np.searchsorted(np.unique(faces), faces),
                                            process=False)) == []
    assert surface.volume == pytest.approx(6.0, rel=1e-14)       # positive: outward
    assert surface_volume(surface) == pytest.approx(6.0, rel=1e-14)


def test_dof_matrix_is_apply_on_the_flat_dofs():
    box = box_tetrahedra(2, 2, 2)
    x, _, _ = inner_points(box.points, box.cells, n=20)
    embedding = embed_points(x, box.points, box.cells)
    keep = torch.tensor([3, 0, 7])                                # some points, any order
    vertices = torch.as_tensor(embedding.vertices)[keep]
    weights = torch.as_tensor(embedding.weights)[keep]
    W = dof_matrix(vertices, weights, embedding.n_vertices, 3)
    assert W.is_coalesced() and W.shape == (9, 3 * embedding.n_vertices)
    moved = torch.as_tensor(box.points) + 0.1 * torch.randn(box.points.shape)
    assert torch.allclose(W @ moved.reshape(-1), embedding.apply(moved)[keep].reshape(-1),
                          rtol=0, atol=1e-14)


def test_every_capsule_vertex_is_reproduced_exactly(capsule):
    surface, points, cells = capsule
    embedding = embed_points(surface.vertices, points, cells, tol=TOL)
    n = len(surface.vertices)
    assert embedding.cells.shape == (n,) and embedding.weights.shape == (n, 4)
    assert embedding.n_vertices == len(points) and embedding.n_points == n
    np.testing.assert_array_equal(embedding.vertices, cells[embedding.cells])
    x = torch.from_numpy(points)
    np.testing.assert_allclose(embedding.apply(x).numpy(), surface.vertices, rtol=0, atol=1e-12)
    np.testing.assert_allclose(embedding.weights.sum(axis=1), 1.0, rtol=0, atol=1e-14)
    inside = embedding.distance == 0
    assert (embedding.weights[inside] >= -TOL).all()
    # fTetWild's boundary is within its envelope of the surface (1e-3 of the diagonal)
    diagonal = np.linalg.norm(np.ptp(surface.vertices, axis=0))
    assert embedding.distance.max() < 2e-3 * diagonal


def test_inside_and_outside_points(capsule):
    surface, points, cells = capsule
    x_in, tets, w_in = inner_points(points, cells)
    x_out = surface.vertices + 0.01 * surface.vertex_normals        # 1 cm outside
    x = np.vstack([x_in, x_out])
    embedding = embed_points(x, points, cells, tol=TOL)
    k = len(x_in)
    # a point strictly inside a tetrahedron belongs to that one only, with its weights
    np.testing.assert_array_equal(embedding.cells[:k], tets)
    np.testing.assert_allclose(embedding.weights[:k], w_in, rtol=0, atol=1e-12)
    assert (embedding.distance[:k] == 0).all()
    # outside: the nearest boundary face by brute force over every (point, face) pair
    faces, owners = boundary_faces(cells)
    tri = points[faces]
    pairs = np.repeat(x_out, len(faces), axis=0), np.tile(tri, (len(x_out), 1, 1))
    close = trimesh.triangles.closest_point(pairs[1], pairs[0]).reshape(len(x_out), -1, 3)
    dist = np.linalg.norm(close - x_out[:, None], axis=2)
    np.testing.assert_allclose(embedding.distance[k:], dist.min(axis=1), rtol=1e-9, atol=1e-13)
    assert (np.abs(embedding.distance[k:] - 0.01) < 2e-3).all()
    # the chosen tetrahedron owns a nearest boundary face
    nearest = np.abs(dist - dist.min(axis=1, keepdims=True)) <= 1e-12
    assert all(embedding.cells[k + i] in set(owners[nearest[i]]) for i in range(len(x_out)))
    # extrapolated weights: still summing to 1 and reproducing the points
    assert embedding.weights[k:].min() < -0.05
    np.testing.assert_allclose(embedding.weights.sum(axis=1), 1.0, rtol=0, atol=1e-13)
    np.testing.assert_allclose(embedding.apply(torch.from_numpy(points)).numpy(), x,
                               rtol=0, atol=1e-12)
    # an affine motion of the mesh moves every embedded point by the same map
    A = np.array([[1.1, 0.2, -0.3], [0.05, 0.9, 0.1], [0.2, -0.1, 1.3]])
    b = np.array([0.3, -0.2, 0.5])
    moved = embedding.apply(torch.from_numpy(points @ A.T + b)).numpy()
    np.testing.assert_allclose(moved, x @ A.T + b, rtol=0, atol=1e-12)


def test_a_point_nearest_an_edge_or_corner_gets_the_same_tetrahedron_when_rotated():
    # outside a box, beyond its edges and corners: as near to two or three boundary faces,
    # whose owners extrapolate differently; the lowest-numbered tied face wins, so the
    # mesh and its rotated copy embed every point in the same tetrahedron
    mesh = box_tetrahedra(3, 2, 4, (1.0, 0.7, 1.3))
    rng = np.random.default_rng(3)
    corner = mesh.points.max(axis=0)
    along_edge = np.stack([corner[0] + 0.02 * rng.random(20), corner[1] + 0.02 * rng.random(20),
                           rng.random(20) * corner[2]], axis=1)
    beyond_corner = corner + 0.03 * rng.random((5, 3))
    x = np.vstack([along_edge, beyond_corner, -0.02 * rng.random((5, 3))])
    faces, owners = boundary_faces(mesh.cells)
    tri = mesh.points[faces]
    close = trimesh.triangles.closest_point(np.tile(tri, (len(x), 1, 1)),
                                            np.repeat(x, len(faces), axis=0))
    dist = np.linalg.norm(close.reshape(len(x), -1, 3) - x[:, None], axis=2)
    tied = dist <= dist.min(axis=1, keepdims=True) * (1 + 1e-9)
    assert (tied.sum(axis=1) >= 2).all()             # every point is a tie
    lowest = np.argmax(tied, axis=1)                 # first True: the lowest face index
    rotation = np.linalg.qr(np.random.default_rng(4).normal(size=(3, 3)))[0]
    plain = embed_points(x, mesh.points, mesh.cells)
    turned = embed_points(x @ rotation.T, mesh.points @ rotation.T, mesh.cells)
    np.testing.assert_array_equal(plain.cells, owners[lowest])
    np.testing.assert_array_equal(turned.cells, plain.cells)
    np.testing.assert_allclose(turned.weights, plain.weights, rtol=0, atol=1e-12)


def test_apply_under_vmap_autograd_and_forward_mode(capsule):
    surface, points, cells = capsule
    embedding = embed_points(surface.vertices, points, cells)
    X = torch.randn(3, len(points), 3)
    loop = torch.stack([embedding.apply(x) for x in X])
    for dim in (0, 1, 2):
        batched = torch.func.vmap(embedding.apply, in_dims=dim)(X.movedim(0, dim))
        torch.testing.assert_close(batched, loop, rtol=0, atol=1e-15)
    torch.testing.assert_close(embedding.apply(X), loop, rtol=0, atol=1e-15)   # leading dims
    W = embedding.matrix()
    assert isinstance(W, scipy.sparse.csr_matrix) and W.shape == (len(surface.vertices),
                                                                 len(points))
    np.testing.assert_allclose(W @ points, embedding.apply(torch.from_numpy(points)).numpy(),
                               rtol=0, atol=1e-15)
    # linear: forward mode gives apply(v); the gradient of <g, apply(x)> is W^T g
    v, g = torch.randn(len(points), 3), torch.randn(len(surface.vertices), 3)
    _, tangent = torch.func.jvp(embedding.apply, (X[0],), (v,))
    torch.testing.assert_close(tangent, embedding.apply(v), rtol=0, atol=1e-15)
    x = X[0].clone().requires_grad_()
    (embedding.apply(x) * g).sum().backward()
    np.testing.assert_allclose(x.grad.numpy(), W.T @ g.numpy(), rtol=0, atol=1e-13)
    y32 = embedding.apply(X[0].float())
    assert y32.dtype == torch.float32
    torch.testing.assert_close(y32.double(), loop[0], rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match=rf"\(\.\.\., {len(points)}, 3\)"):
        embedding.apply(X[0, :-1])


def test_points_too_far_outside_are_named(capsule):
    surface, points, cells = capsule
    x = surface.vertices[:5].copy()
    x[3] = [1.0, 0.0, 0.0]                         # 0.955 m beside the capsule (r 0.045)
    with pytest.raises(MeshError, match=r"point 3 lies 0\.\d+ outside the tetrahedral mesh, "
                                        r"more than max_distance=0\.01 \(1 point"):
        embed_points(x, points, cells, max_distance=0.01)
    embedding = embed_points(x, points, cells)     # without a limit: extrapolated
    assert embedding.distance[3] == pytest.approx(0.955, abs=2e-3)
    np.testing.assert_allclose(embedding.matrix() @ points, x, rtol=0, atol=1e-12)
    with pytest.raises(MeshError, match="positively oriented"):
        embed_points(x, points, cells[:, [0, 2, 1, 3]])
    assert isinstance(embedding, Embedding)

"""Embedding of dense points in a tet mesh (preprocessing) and the per-frame map_dense kernel."""

import numpy as np
import pytest
import trimesh
import warp as wp

from warpfem.prep.embedding import embed
from warpfem.prep.tetmesh import tetrahedralize
from warpfem.sim.embedding import map_dense


@pytest.fixture(scope="module")
def ball():
    """A coarse tet-meshed sphere of radius 1 and its boundary."""
    sphere = trimesh.creation.icosphere(subdivisions=1)
    points, tets = tetrahedralize(sphere.vertices, sphere.faces, maxh=0.5)
    return points, tets, np.asarray(sphere.faces, dtype=np.int32)


def _all_barycentrics(p, points, tets):
    """(len(tets), 4) barycentric coordinates of p in every tet, by brute force."""
    a = points[tets[:, 0]]
    dm = np.stack([points[tets[:, k]] - a for k in (1, 2, 3)], axis=2)
    local = np.linalg.solve(dm, (p - a)[:, :, None])[:, :, 0]
    return np.concatenate([1 - local.sum(axis=1, keepdims=True), local], axis=1)


def _point_triangle_distance(p, tri):
    """Distance from p to triangle tri (3, 3), by dense sampling of barycentric coordinates."""
    s = np.linspace(0, 1, 81)
    u, v = np.meshgrid(s, s)
    keep = u + v <= 1
    u, v = u[keep], v[keep]
    samples = np.outer(1 - u - v, tri[0]) + np.outer(u, tri[1]) + np.outer(v, tri[2])
    return np.linalg.norm(samples - p, axis=1).min()


def test_embedding_reproduces_inside_and_outside_points(ball):
    points, tets, boundary = ball
    rng = np.random.default_rng(1)
    directions = rng.normal(size=(400, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    queries = directions * rng.uniform(0.0, 1.15, size=(400, 1))  # the coarse sphere's facets dip to ~0.8
    tet_index, bary = embed(queries, points, tets, boundary)
    assert tet_index.dtype == np.int32 and bary.shape == (400, 4)

    rebuilt = np.einsum("nk,nkj->nj", bary, points[tets[tet_index]])
    np.testing.assert_allclose(rebuilt, queries, atol=1e-5 * 2.0)
    np.testing.assert_allclose(bary.sum(axis=1), 1.0, atol=1e-12)

    best = np.array([_all_barycentrics(q, points, tets).min(axis=1).max() for q in queries])
    inside = best >= -1e-9  # brute force: inside some tet
    assert 50 < inside.sum() < 350
    assert np.all(bary[inside].min(axis=1) >= -1e-5)  # assigned to a tet containing it
    assert np.all(bary[best < -1e-4].min(axis=1) < -1e-4)  # outside points extrapolate

    tris = points[boundary]
    for i in np.flatnonzero(~inside)[:40]:
        nearest = min(_point_triangle_distance(queries[i], t) for t in tris)
        # the assigned tet owns a boundary face at that nearest distance
        owned = [t for t in tris if set(map(tuple, t)) <= set(map(tuple, points[tets[tet_index[i]]]))]
        assert owned, "outside point assigned to a tet without a boundary face"
        assert min(_point_triangle_distance(queries[i], t) for t in owned) == pytest.approx(nearest, abs=1e-2)


def test_embedding_of_tet_vertices_is_exact(ball):
    points, tets, boundary = ball
    tet_index, bary = embed(points, points, tets, boundary)
    assert np.all(bary.min(axis=1) >= -1e-9)
    assert np.allclose(bary.max(axis=1), 1.0)
    assert np.all(np.any(tets[tet_index] == np.arange(len(points))[:, None], axis=1))


def test_map_dense_matches_einsum(device):
    rng = np.random.default_rng(7)
    positions = rng.normal(size=(50, 3))
    tets = rng.integers(0, 50, size=(30, 4)).astype(np.int32)
    dense_tet = rng.integers(0, 30, size=1000).astype(np.int32)
    bary = rng.normal(size=(1000, 4))
    expected = np.einsum("nk,nkj->nj", bary, positions[tets[dense_tet]])

    out = wp.zeros(1000, dtype=wp.vec3, device=device)
    map_dense(
        wp.array(tets, dtype=wp.vec4i, device=device),
        wp.array(positions, dtype=wp.vec3, device=device),
        wp.array(dense_tet, dtype=wp.int32, device=device),
        wp.array(bary, dtype=wp.vec4, device=device),
        out,
    )
    np.testing.assert_allclose(out.numpy(), expected, rtol=1e-5, atol=1e-5)


def test_deformed_mesh_moves_embedded_points_affinely(ball, device):
    points, tets, boundary = ball
    dense = trimesh.creation.icosphere(subdivisions=3, radius=0.95).vertices
    tet_index, bary = embed(dense, points, tets, boundary)
    affine = np.array([[1.2, 0.1, 0.0], [0.0, 0.9, 0.3], [0.2, 0.0, 1.1]])
    shift = np.array([0.5, -1.0, 2.0])
    out = wp.zeros(len(dense), dtype=wp.vec3, device=device)
    map_dense(
        wp.array(tets, dtype=wp.vec4i, device=device),
        wp.array(points @ affine.T + shift, dtype=wp.vec3, device=device),
        wp.array(tet_index, dtype=wp.int32, device=device),
        wp.array(bary, dtype=wp.vec4, device=device),
        out,
    )
    # barycentric (and extrapolated) coordinates reproduce any affine map exactly
    np.testing.assert_allclose(out.numpy(), dense @ affine.T + shift, atol=1e-5)

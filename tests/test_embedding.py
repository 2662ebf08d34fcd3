"""Embedding of dense points in a tet mesh (preprocessing) and the per-frame map_dense kernel."""

import numpy as np
import pytest
import trimesh
import warp as wp

from warpfem.prep.embedding import embed, outside_distance
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
        distances = np.array([_point_triangle_distance(queries[i], t) for t in tris])
        near = np.flatnonzero(distances <= distances.min() + 1e-2)  # the nearest face, up to the sampling
        # the assigned tet touches a corner of a nearest boundary face, and of the tets that do, none
        # reproduces the point with smaller weights (their absolute values summed)
        touching = [np.flatnonzero(np.isin(tets, boundary[f]).any(axis=1)) for f in near]
        assert any(tet_index[i] in t for t in touching), "outside point assigned away from its nearest face"
        spread = np.abs(_all_barycentrics(queries[i], points, tets)).sum(axis=1)
        assert np.abs(bary[i]).sum() <= min(spread[t].min() for t in touching) + 1e-9


def _capped_cube(cap: float):
    """The unit cube in six tets, its top face under a pyramid of two flat tets rising ``cap`` above it."""
    corner = np.array([[(i >> a) & 1 for a in range(3)] for i in range(8)], dtype=np.float64)
    points = np.vstack([corner, [[0.5, 0.5, 1.0 + cap]]])
    tets = []
    for order in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        path = [0, 1 << order[0], (1 << order[0]) | (1 << order[1]), 7]
        tets.append(path)
    top = [v for v in range(8) if corner[v, 2] == 1.0]  # 4, 5, 6, 7
    tets += [[top[0], top[1], top[3], 8], [top[0], top[3], top[2], 8]]
    tets = np.array(tets, dtype=np.int32)
    for t in tets:  # positively oriented
        if np.linalg.det(np.stack([points[t[k]] - points[t[0]] for k in (1, 2, 3)], axis=1)) < 0:
            t[[1, 2]] = t[[2, 1]]
    faces = np.sort(np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 2, 3]], tets[:, [0, 1, 3]], tets[:, [0, 1, 2]]]), 1)
    unique, counts = np.unique(faces, axis=0, return_counts=True)
    return points, tets, unique[counts == 1].astype(np.int32)


def test_a_point_off_a_sliver_follows_the_body_not_the_sliver():
    """A point just above a cube whose top is capped by flat tets (1 mm high over 1 m): the cap's tets own
    the nearest faces but would give the point weights of tens; it is embedded where its weights stay near
    those of a point in a tet, so jiggling the tet vertices by 1 mm moves it by millimetres, not centimetres."""
    points, tets, boundary = _capped_cube(1e-3)
    queries = np.array([[0.3, 0.6, 1.05], [0.7, 0.45, 1.02], [0.52, 0.5, 1.1]])
    tet_index, bary = embed(queries, points, tets, boundary)
    np.testing.assert_allclose(np.einsum("nk,nkj->nj", bary, points[tets[tet_index]]), queries, atol=1e-9)
    for q in queries:  # the cap's tets would extrapolate by tens
        assert np.abs(_all_barycentrics(q, points, tets)[-2:]).sum(axis=1).min() > 20.0
    assert np.abs(bary).sum(axis=1).max() < 1.5
    rng = np.random.default_rng(2)
    for _ in range(20):
        moved = points + rng.normal(scale=1e-3, size=points.shape)
        mapped = np.einsum("nk,nkj->nj", bary, moved[tets[tet_index]])
        assert np.linalg.norm(mapped - queries, axis=1).max() < 5e-3


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


def test_outside_distance_is_the_distance_past_the_face_a_point_lies_beside():
    """Against the geometry worked by hand: a right tet with legs 2 (corners at the origin and on the axes),
    points 0.3 past its face x = 0, 0.1 past its slanted face x + y + z = 2 (distance measured along that face's
    normal), one inside and one at a corner: 0.3, 0.1, 0 and 0."""
    corners = np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0], [0, 0, 2]], dtype=np.float64)
    tets = np.array([[0, 1, 2, 3]])
    unit = np.ones(3) / np.sqrt(3.0)
    points = np.array([[-0.3, 0.5, 0.5], [2 / 3, 2 / 3, 2 / 3] + 0.1 * unit, [0.3, 0.3, 0.3], [2.0, 0.0, 0.0]])
    # barycentrics solved independently: p = w0 c0 + w1 c1 + w2 c2 + w3 c3 with the weights summing to one
    system = np.vstack([corners.T, np.ones(4)])
    bary = np.linalg.solve(system, np.vstack([points.T, np.ones(len(points))])).T
    past = outside_distance(corners, tets, np.zeros(len(points), dtype=np.int32), bary)
    np.testing.assert_allclose(past, [0.3, 0.1, 0.0, 0.0], atol=1e-12)

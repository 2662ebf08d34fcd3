"""Distance field at tet vertices: depth below the surface and its outward gradient."""

import numpy as np
import pytest
import trimesh

from warpfem.prep.distance import distance_field
from warpfem.prep.tetmesh import tetrahedralize


def test_sphere_depth_and_gradient_against_the_analytic_field():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    points, _ = tetrahedralize(sphere.vertices, sphere.faces, maxh=0.25)
    depth, grad = distance_field(points, sphere.vertices, sphere.faces)
    assert depth.shape == (len(points),) and grad.shape == (len(points), 3)

    # the polyhedron lies between the sphere and the ball of radius `facet` (its facets' closest approach)
    tris = sphere.vertices[sphere.faces]
    normals = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    facet = np.min(np.abs(np.einsum("ij,ij->i", normals, tris[:, 0])) / np.linalg.norm(normals, axis=1))
    r = np.linalg.norm(points, axis=1)
    np.testing.assert_array_less(np.abs(depth - (1.0 - r)), (1.0 - facet) + 1e-6)
    assert len(points) > len(sphere.vertices) + 20  # there are interior vertices to test

    on_surface = np.arange(len(sphere.vertices))
    assert np.all(depth[on_surface] == 0.0)
    radial = points / r[:, None]
    # surface vertices: area-weighted normal of the icosphere, radial to within the facet angles
    assert np.all(np.einsum("ij,ij->i", grad[on_surface], radial[on_surface]) > 0.999)
    interior = r < 0.9
    cosine = np.einsum("ij,ij->i", grad[interior & (r > 0.3)], radial[interior & (r > 0.3)])
    assert np.all(cosine > 0.95)
    np.testing.assert_allclose(np.linalg.norm(grad, axis=1), 1.0, atol=1e-9)


def test_box_depth_matches_the_analytic_distance():
    half = np.array([1.0, 0.5, 0.25])
    box = trimesh.creation.box(extents=2 * half)
    rng = np.random.default_rng(3)
    inner = rng.uniform(-half, half, size=(500, 3)) * 0.999
    queries = np.vstack([inner, box.vertices])
    depth, grad = distance_field(queries, box.vertices, box.faces)

    gaps = half - np.abs(inner)
    np.testing.assert_allclose(depth[:500], gaps.min(axis=1), atol=1e-5)
    axis = gaps.argmin(axis=1)
    clear = np.sort(gaps, axis=1)[:, 1] - gaps.min(axis=1) > 1e-3  # the nearest face is unambiguous
    expected = np.zeros_like(inner)
    expected[np.arange(500), axis] = np.sign(inner[np.arange(500), axis])
    np.testing.assert_allclose(grad[:500][clear], expected[clear], atol=1e-4)

    corners = box.vertices
    assert np.all(depth[500:] == 0.0)
    # area-weighted normals at a box corner point outward into the corner's octant
    assert np.all(np.sign(grad[500:]) == np.sign(corners))


@pytest.mark.parametrize("scale", [1e-3, 1e3])
def test_depth_scales_with_the_mesh(scale):
    sphere = trimesh.creation.icosphere(subdivisions=2)
    queries = np.array([[0.5, -0.1, 0.2], [0.3, 0.2, -0.1]])
    depth_1, grad_1 = distance_field(queries, sphere.vertices, sphere.faces)
    depth_s, grad_s = distance_field(scale * queries, scale * sphere.vertices, sphere.faces)
    np.testing.assert_allclose(depth_s, scale * depth_1, rtol=1e-5)
    np.testing.assert_allclose(grad_s, grad_1, atol=1e-4)


def test_sample_hausdorff_of_a_shifted_sphere():
    from warpfem.prep.distance import hausdorff

    sphere = trimesh.creation.icosphere(subdivisions=4)
    a_to_b, b_to_a = hausdorff(sphere.vertices, sphere.faces, sphere.vertices + [0.05, 0.0, 0.0], sphere.faces)
    # for two unit spheres 0.05 apart the distance is 0.05, reached at the poles on the x axis
    assert a_to_b == pytest.approx(0.05, rel=0.02) and b_to_a == pytest.approx(0.05, rel=0.02)

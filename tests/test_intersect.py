"""Self-intersection detection (warpfem.prep.intersect) against libigl's triangle-triangle test."""

import igl
import numpy as np
import pytest
import trimesh

from warpfem.prep.intersect import intersecting_faces
from warpfem.prep.surface import load_surface


def _reference_pairs(vertices, faces):
    """All intersecting pairs of faces with no shared vertex, by igl's Guigue-Devillers test."""
    pairs = set()
    for i in range(len(faces)):
        for j in range(i + 1, len(faces)):
            if set(faces[i]) & set(faces[j]):
                continue
            tri = [vertices[faces[i][k]][None, :] for k in range(3)] + [
                vertices[faces[j][k]][None, :] for k in range(3)
            ]
            hit, coplanar, _, _ = igl.tri_tri_intersection_test_3d(*tri)
            if hit and not coplanar:
                pairs.add((i, j))
    return pairs


def test_random_triangle_soup_matches_libigl():
    rng = np.random.default_rng(7)
    centers = rng.random((80, 1, 3))
    vertices = (centers + 0.6 * (rng.random((80, 3, 3)) - 0.5)).reshape(-1, 3)
    faces = np.arange(len(vertices)).reshape(-1, 3)
    expected = _reference_pairs(vertices, faces)
    assert 20 < len(expected) < 1000  # the soup is dense enough to test both outcomes
    pairs, mask = intersecting_faces(vertices, faces)
    assert pairs == len(expected)
    involved = np.zeros(len(faces), dtype=bool)
    involved[[i for pair in expected for i in pair]] = True
    np.testing.assert_array_equal(mask, involved)


def test_closed_sphere_has_none_and_two_crossing_spheres_meet_on_a_circle():
    sphere = trimesh.creation.icosphere(subdivisions=3)
    assert intersecting_faces(sphere.vertices, sphere.faces)[0] == 0
    moved = sphere.vertices + [1.2, 0.0, 0.0]
    vertices = np.vstack([sphere.vertices, moved])
    faces = np.vstack([sphere.faces, sphere.faces + len(sphere.vertices)])
    pairs, mask = intersecting_faces(vertices, faces)
    assert pairs > 0
    # every flagged face is near the circle where the unit spheres cross: x = 0.6, radius 0.8
    centroids = vertices[faces[mask]].mean(axis=1)
    x = centroids[:, 0]
    assert np.all(np.abs(x - 0.6) < 0.1)
    far = trimesh.creation.icosphere(subdivisions=3).vertices + [2.5, 0.0, 0.0]
    assert intersecting_faces(np.vstack([sphere.vertices, far]), faces)[0] == 0


@pytest.mark.parametrize("through", [True, False])
def test_faces_sharing_a_corner(through):
    # triangle B shares corner 0 with A; its far edge crosses A's plane inside A, or where the line from
    # the shared corner misses A (then the two meet only at that corner)
    x, y = (1.0, 0.2) if through else (-1.0, 1.0)
    vertices = np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0], [x, y, -1], [x, y, 1]], dtype=float)
    faces = np.array([[0, 1, 2], [0, 3, 4]])
    assert intersecting_faces(vertices, faces)[0] == int(through)


def test_neighbours_and_scale_do_not_matter():
    # a folded strip of two triangles sharing an edge is never reported; a huge scale changes nothing
    sphere = trimesh.creation.icosphere(subdivisions=2)
    for scale in (1e-9, 1.0, 1e12):
        assert intersecting_faces(sphere.vertices * scale, sphere.faces)[0] == 0
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.2, 0.2, 0]], dtype=float)
    assert intersecting_faces(vertices, np.array([[0, 1, 2], [1, 0, 3]]))[0] == 0


def test_cow_intersects_itself(asset):
    surface = load_surface(asset("cow.obj"))
    pairs, mask = intersecting_faces(surface.vertices, surface.faces)
    assert pairs == 81  # measured independently with libigl (docs: measured.md)
    assert 81 <= mask.sum() <= 162


def test_coplanar_faces_sharing_a_corner_do_not_cross():
    """Two faces of one flat strip of a remeshed CAD part (points off their common plane by rounding only),
    sharing one corner, with two far triangles that fix the bounding box: they touch at that corner only."""
    points = [
        [-0.26432743668556213, -0.19163739681243896, 0.13216371834278107],
        [-0.23128651082515717, -0.19163739681243896, 0.13216371834278107],
        [-0.26432743668556213, -0.13418037732706944, 0.07470669885741155],
        [-0.23128651082515717, -0.1157305276402476, 0.05625684917058971],
        [-0.23128651082515717, -0.15496200179586878, 0.09548832332621088],
        [-0.3964911699295044, -0.23128651082515717, -0.1982455849647522],
        [-0.3954911699295044, -0.23128651082515717, -0.1982455849647522],
        [-0.3964911699295044, -0.23028651082515716, -0.1982455849647522],
        [0.3964911699295044, 0.23128651082515717, 0.1982455849647522],
        [0.3954911699295044, 0.23128651082515717, 0.1982455849647522],
        [0.3964911699295044, 0.23028651082515716, 0.1982455849647522],
    ]
    faces = np.array([[4, 3, 2], [0, 1, 4], [5, 6, 7], [8, 9, 10]])
    assert intersecting_faces(np.array(points), faces)[0] == 0

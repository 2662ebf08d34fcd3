"""The independent penetration check of dense meshes, against analytic sphere overlaps."""

import numpy as np
import pytest
import trimesh

from warpfem.io.penetration import Obstacle, Penetration, measure


def _sphere(center, radius, subdivisions=5):
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(s.vertices) + center, np.asarray(s.faces)


def test_overlapping_spheres_give_the_analytic_depth():
    """Each sphere's vertices reach r_a + r_b - d into the other; relative to the smaller, b, it is deepest."""
    (va, fa), (vb, fb) = _sphere((0, 0, 0), 0.5), _sphere((0.7, 0, 0), 0.3)
    result = measure([va, vb], [fa, fb], ["a", "b"])
    assert result.inside == "a in b"
    assert result.depth == pytest.approx(0.5 + 0.3 - 0.7, abs=2e-3)
    size_b = np.linalg.norm(vb.max(0) - vb.min(0))
    assert result.relative == pytest.approx(result.depth / size_b)


def test_apart_and_nested_bodies():
    (va, fa), (vb, fb) = _sphere((0, 0, 0), 0.5), _sphere((1.2, 0, 0), 0.3)
    assert measure([va, vb], [fa, fb], ["a", "b"]) == Penetration()
    small_v, small_f = _sphere((0.2, 0, 0), 0.1)  # wholly inside a: its vertex nearest a's centre is 0.4 deep
    result = measure([va, small_v], [fa, small_f], ["a", "small"])
    assert result.inside == "small in a" and result.depth == pytest.approx(0.4, abs=2e-3)


def test_ground_depth_is_the_lowest_point_below_the_plane():
    v, f = _sphere((0, 0.45, 0), 0.5)
    result = measure([v], [f], ["a"], ground=(0.0, (0.0, 1.0, 0.0)))
    assert result.below_ground == pytest.approx(0.05, abs=1e-3) and result.depth == 0.0
    z_up = measure([v[:, [0, 2, 1]]], [f], ["a"], ground=(0.1, (0.0, 0.0, 2.0)))  # any up, normalised
    assert z_up.below_ground == pytest.approx(0.15, abs=1e-3)
    assert measure([v + [0, 1, 0]], [f], ["a"], ground=(0.0, (0.0, 1.0, 0.0))).below_ground == 0.0


def test_worst_keeps_the_deeper_of_each_measure():
    a = Penetration(0.01, 0.02, "x in y", 0.0, 0.0)
    b = Penetration(0.02, 0.01, "y in x", 0.003, 0.001)
    assert a.worst(b) == Penetration(0.01, 0.02, "x in y", 0.003, 0.001)


def test_obstacles_count_as_ground():
    v, f = _sphere((0, 0, 0), 0.5)
    ball = Obstacle(center=(0.0, -0.6, 0.0), radius=0.2)  # the body's bottom reaches 0.1 into it
    box = Obstacle(center=(0.0, 0.55, 0.0), half_extents=(1.0, 0.1, 1.0))  # its top reaches 0.05 into it
    assert measure([v], [f], ["a"], obstacles=[ball]).below_ground == pytest.approx(0.1, abs=1e-3)
    assert measure([v], [f], ["a"], obstacles=[box]).below_ground == pytest.approx(0.05, abs=1e-3)
    assert measure([v], [f], ["a"], obstacles=[ball, box], bodies=False).below_ground == pytest.approx(0.1, abs=1e-3)

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


def _reference(points, faces, names):
    """The worst body-inside-body penetration by libigl's exact winding number and point-to-mesh distance."""
    import igl

    sizes = [np.linalg.norm(np.ptp(p, axis=0)) for p in points]
    worst = (0.0, 0.0, "")
    for j, (v, f) in enumerate(zip(points, faces, strict=True)):
        for i, q in enumerate(points):
            if i == j:
                continue
            q = q[np.all((q >= v.min(0)) & (q <= v.max(0)), axis=1)]
            inside = q[igl.winding_number(v, f, q) > 0.5]
            if len(inside):
                depth, *_ = igl.signed_distance(inside, v, f, sign_type=igl.SIGNED_DISTANCE_TYPE_UNSIGNED)
                depth = float(np.abs(depth).max())
                if depth / sizes[j] > worst[1]:
                    worst = (depth, depth / sizes[j], f"{names[i]} in {names[j]}")
    return worst


def test_overlapping_bunnies_agree_with_libigl_exact_winding_numbers(device):
    """Two bunnies (one turned and scaled) in two poses, measured by one check (its meshes refitted)."""
    import warp as wp
    from scipy.spatial.transform import Rotation

    from warpfem.io.penetration import BodyBounds, PenetrationCheck
    from warpfem.prep.surface import load_surface

    bunny = load_surface("builtin:bunny")
    v, f = np.asarray(bunny.vertices, np.float64), np.asarray(bunny.faces, np.int64)
    size = np.linalg.norm(np.ptp(v, axis=0))
    turned = 0.8 * Rotation.from_euler("xyz", [20, 70, -10], degrees=True).apply(v - v.mean(0)) + v.mean(0)
    check = PenetrationCheck([f, f], ["a", "b"], device)
    on_device = PenetrationCheck([f, f], ["a", "b"], device)  # the points where a simulation maps them
    bounds = BodyBounds([(0, len(v)), (len(v), 2 * len(v))], device)
    for offset in ([0.3, 0.05, 0.0], [0.15, -0.1, 0.2]):
        points = [v, turned + np.multiply(offset, size)]
        depth, relative, inside = _reference(points, [f, f], ["a", "b"])
        flat = wp.array(np.concatenate(points).astype(np.float32), dtype=wp.vec3, device=device)
        on_device.start_bodies(flat, [len(v), len(v)], bounds.compute(flat))
        for result in (check.measure([p.astype(np.float32) for p in points]), on_device.collect_bodies()):
            assert relative > 0.05 and result.inside == inside
            assert result.depth == pytest.approx(depth, abs=1e-5 * size)
            assert result.relative == pytest.approx(relative, abs=1e-5)


def test_bad_boxes_ranges_and_body_check_order_are_named(device):
    """Boxes of the wrong shape, ranges that do not follow each other, points of the wrong count, and a body
    check collected before it started or started twice: each a one-line error saying what is wrong."""
    import warp as wp

    from warpfem.io.penetration import BodyBounds, PenetrationCheck

    tet = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    corners = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    check = PenetrationCheck([tet, tet], ["a", "b"], device)
    with pytest.raises(ValueError, match=r"boxes must be a \(2, 2, 3\) array, got shape \(1, 2, 3\)"):
        check.measure([corners, corners + 0.5], boxes=np.zeros((1, 2, 3)))
    with pytest.raises(ValueError, match=r"body 1: points 5\.\.8 do not follow the previous body's \(end 4\)"):
        BodyBounds([(0, 4), (5, 8)], device)
    with pytest.raises(RuntimeError, match="no body check was started"):
        check.collect_bodies()
    flat = wp.array(np.concatenate([corners, corners + 0.5]), dtype=wp.vec3, device=device)
    bounds = BodyBounds([(0, 4), (4, 8)], device).compute(flat)
    check.start_bodies(flat, [4, 4], bounds)
    with pytest.raises(RuntimeError, match="collect the previous body check first"):
        check.start_bodies(flat, [4, 4], bounds)
    check.collect_bodies()
    with pytest.raises(ValueError, match="4 points given, 8 expected"):
        check.start_bodies(flat[:4], [4, 4], bounds)

"""The independent penetration check of dense meshes, against analytic sphere overlaps."""

from pathlib import Path

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


def _box_mesh():
    """A unit cube's closed, outward-wound surface centred on the origin (m)."""
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    return np.asarray(box.vertices, np.float64), np.asarray(box.faces, np.int64)


def _plate(n=4):
    """An open 2 m x 2 m square plate at y = 0 facing +y, of n x n quads (two triangles each)."""
    x = np.linspace(-1.0, 1.0, n + 1)
    gx, gz = np.meshgrid(x, x, indexing="ij")
    v = np.stack([gx.ravel(), np.zeros(gx.size), gz.ravel()], axis=1)
    k = np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]
    k = k.ravel()
    f = np.concatenate([np.stack([k, k + 1, k + n + 2], 1), np.stack([k, k + n + 2, k + n + 1], 1)])
    return v, f


def _pose(degrees, translation):
    """A 4x4 rotation about each axis by ``degrees`` then a translation (column vectors)."""
    from scipy.spatial.transform import Rotation

    m = np.eye(4)
    m[:3, :3] = Rotation.from_euler("xyz", degrees, degrees=True).as_matrix()
    m[:3, 3] = translation
    return m


def _world(m, local):
    return local @ m[:3, :3].T + m[:3, 3]


def _libigl_depth(p, v, f, closed, reach):
    """Depth in a mesh by libigl in float64: exact winding number and distance (closed), or behind the nearest
    face within reach, its nearest point off any edge no other face shares (open)."""
    import igl

    if closed:
        inside = igl.winding_number(v, f, p) > 0.5
        distance, *_ = igl.signed_distance(p, v, f, sign_type=igl.SIGNED_DISTANCE_TYPE_UNSIGNED)
        return np.where(inside, np.abs(distance), 0.0)
    squared, face, nearest = igl.point_mesh_squared_distance(p, v, f)
    a, b, c = (v[f[face, k]] for k in range(3))
    behind = np.einsum("ij,ij->i", p - nearest, np.cross(b - a, c - a)) < 0
    edges = np.sort(np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], axis=1), axis=2).reshape(-1, 2)
    _, inverse, counts = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    lone = (counts[inverse.reshape(-1)] == 1).reshape(-1, 3)
    rim = np.zeros(len(v), bool)
    rim[np.concatenate([f[lone[:, 0]][:, [0, 1]], f[lone[:, 1]][:, [1, 2]], f[lone[:, 2]][:, [2, 0]]]).ravel()] = True
    w = igl.barycentric_coordinates(nearest, a, b, c) < 1e-5
    near_edge = w[:, [2, 0, 1]]  # edge a-b where c's weight is 0, b-c where a's, c-a where b's
    at_corner = np.stack([w[:, 1] & w[:, 2], w[:, 2] & w[:, 0], w[:, 0] & w[:, 1]], axis=1)
    on_open = (lone[face] & near_edge).any(axis=1) | (rim[f[face]] & at_corner).any(axis=1)
    depth = np.sqrt(squared)
    return np.where(behind & ~on_open & (depth <= reach), depth, 0.0)


@pytest.mark.parametrize("pose", [None, ((30.0, -50.0, 10.0), (0.4, 1.2, -0.3))])
def test_a_closed_box_mesh_gives_the_analytic_depth_inside_and_none_outside(pose):
    """Points inside a unit cube mesh are as deep as their distance to the nearest side; outside, 0; the same
    cube turned and moved (its matrix) gives the same depths at the moved points."""
    v, f = _box_mesh()
    rng = np.random.default_rng(3)
    local = np.concatenate([rng.uniform(-0.49, 0.49, (300, 3)), rng.uniform(-1.5, 1.5, (300, 3))])
    local = local[np.abs(np.abs(local).max(axis=1) - 0.5) > 1e-3]  # none on the surface
    m = None if pose is None else _pose(*pose)
    p = local if m is None else _world(m, local)
    expected = np.maximum(0.5 - np.abs(local).max(axis=1), 0.0)
    depth = Obstacle(mesh=(v, f, True, 1.0), matrix=m).depth(p)
    assert depth == pytest.approx(expected, abs=1e-6)
    assert depth[:3] == pytest.approx(_libigl_depth(local[:3], v, f, True, 1.0), abs=1e-6)
    inside = np.array([[0.1, 0.2, -0.15]])  # 0.3 from the side at y = 0.5
    world = inside if m is None else _world(m, inside)
    result = measure([world], [np.zeros((0, 3), int)], ["a"], obstacles=[Obstacle(mesh=(v, f, True, 1.0), matrix=m)])
    assert result.below_ground == pytest.approx(0.3, abs=1e-6)


@pytest.mark.parametrize("pose", [None, ((-20.0, 15.0, 35.0), (-1.0, 0.5, 2.0))])
def test_an_open_plate_holds_points_behind_it_within_reach_and_not_past_its_open_edges(pose):
    """Behind a plate facing +y (y < 0) within reach over its inside: the distance; in front, beyond reach, or
    past its open edges and corners (the nearest point on them): 0. Moved by its matrix, the same."""
    v, f = _plate()
    reach = 0.1
    local = np.array(
        [
            [0.3, -0.05, 0.2],  # behind, inside the footprint: 0.05
            [-0.9, -0.099, 0.95],  # behind near a corner, still over the plate: 0.099
            [0.0, -0.0995, 0.0],  # just within reach under an inner vertex: 0.0995
            [0.3, 0.05, 0.2],  # in front
            [0.3, -0.15, 0.2],  # beyond reach
            [1.05, -0.02, 0.0],  # past the open edge at x = 1: its nearest point is on it
            [1.03, -0.01, -1.03],  # past the open corner (1, 0, -1)
            [0.5, -0.03, -1.0],  # under the open edge at z = -1 exactly
        ]
    )
    expected = np.array([0.05, 0.099, 0.0995, 0.0, 0.0, 0.0, 0.0, 0.0])
    m = None if pose is None else _pose(*pose)
    p = local if m is None else _world(m, local)
    plate = Obstacle(mesh=(v, f, False, reach), matrix=m)
    assert plate.depth(p) == pytest.approx(expected, abs=1e-6)
    assert _libigl_depth(local, v, f, False, reach) == pytest.approx(expected, abs=1e-12)
    bodies = [p[:3], p[3:]]  # the deepest per body, folded on the device
    result = measure(bodies, [np.zeros((0, 3), int)] * 2, ["a", "b"], obstacles=[plate], bodies=False)
    assert result.below_ground == pytest.approx(0.0995, abs=1e-6)
    assert measure([p[3:]], [np.zeros((0, 3), int)], ["b"], obstacles=[plate]).below_ground == 0.0


@pytest.mark.parametrize("closed", [True, False])
def test_mesh_obstacle_depths_agree_with_libigl_on_a_moved_bunny_and_bowl(closed):
    """Random points around a closed bunny, or an open hemispherical bowl (reach 5% of its size), each turned
    and moved by its matrix: the depths agree with libigl's in float64 to float32 precision."""
    from warpfem.prep.surface import load_surface

    if closed:
        surface = load_surface("builtin:bunny")
        v, f = np.asarray(surface.vertices, np.float64), np.asarray(surface.faces, np.int64)
    else:
        bowl = trimesh.load(Path(__file__).resolve().parents[1] / "scenes" / "meshes" / "bowl.obj", force="mesh")
        v, f = np.asarray(bowl.vertices, np.float64), np.asarray(bowl.faces, np.int64)
    size = float(np.linalg.norm(np.ptp(v, axis=0)))
    reach = size if closed else 0.05 * size
    rng = np.random.default_rng(7)
    low, high = v.min(0) - 0.1 * size, v.max(0) + 0.1 * size
    local = np.concatenate([rng.uniform(low, high, (4000, 3)), v[f[:, 0]] + rng.normal(0, 0.02 * size, (len(f), 3))])
    expected = _libigl_depth(local, v, f, closed, reach)
    assert (expected > 0).sum() > 200
    m = _pose((25.0, 40.0, -15.0), (0.3, -0.7, 1.1))
    depth = Obstacle(mesh=(v, f, closed, reach), matrix=m).depth(_world(m, local))
    assert depth == pytest.approx(expected, abs=1e-6 * size)

"""Body-body and self collisions: stacking, momentum, thin parts, and paying only for what a scene uses."""

import functools

import numpy as np
import pytest
import warp as wp

import warpfem
from warpfem.build import add_body
from warpfem.prep.distance import distance_field
from warpfem.prep.geometry import tet_tree
from warpfem.prep.shapes import box_tet_mesh
from warpfem.prep.tetmesh import boundary_faces
from warpfem.sim.cg import CGSolver
from warpfem.sim.collision import CollisionSettings
from warpfem.sim.model import ModelBuilder
from warpfem.sim.solver import Ground, Solver


def _box(lo, size, cells):
    hi = tuple(np.add(lo, size))
    return box_tet_mesh(lo, hi, cells)


def _run(solver, model, steps, dt, each=None):
    s0, s1 = model.state(), model.state()
    for _ in range(steps):
        solver.step(s0, s1, dt)
        s0, s1 = s1, s0
        if each:
            each(s0)
    return s0


def inside_tets(points, vertices, tets, tol=0.0):
    """(points, tets) bool: whether each tet (vertices, tets) holds each point, by NumPy barycentrics, each
    weight allowed down to ``-tol``."""
    A = np.stack([vertices[tets[:, k]] - vertices[tets[:, 0]] for k in (1, 2, 3)], axis=2)
    b = np.einsum("tij,ptj->pti", np.linalg.inv(A), points[:, None, :] - vertices[tets[:, 0]][None])
    return (b >= -tol).all(axis=2) & (b.sum(axis=2) <= 1 + tol)


def penetration(points, vertices, tets):
    """Deepest of ``points`` inside the deformed tet mesh (vertices, tets): 0 if none is inside.

    Inside: a barycentric test against every tet (NumPy); depth: the distance to the mesh's boundary.
    """
    inside = inside_tets(points, vertices, tets).any(axis=1)
    if not inside.any():
        return 0.0
    depth, _ = distance_field(points[inside], vertices, boundary_faces(tets))
    return float(depth.max())


def test_two_cubes_come_to_rest_stacked(device):
    b = ModelBuilder()
    add_body(b, "a", *_box((0, 0, 0), (0.2, 0.2, 0.2), (3, 3, 3)), 1e5, 0.3, 1000.0, damping_stiffness=0.01)
    add_body(
        b, "b", *_box((0.025, 0.3, 0.025), (0.15, 0.15, 0.15), (3, 3, 3)), 1e5, 0.3, 1000.0, damping_stiffness=0.01
    )
    model = b.finalize(device)
    solver = Solver(model, ground=Ground(), cg_iterations=200, cg_tolerance=1e-5, collision=CollisionSettings())
    x = _run(solver, model, 480, 1 / 240).x.numpy()
    assert solver.first_bad_vertex() is None
    a, top = model.bodies
    xa = x[: a.vertex_count]
    xb = x[top.vertex_start :]
    _, _, deepest, overflow = solver.collider.read_stats()
    assert not overflow
    # b rests on a: its bottom sits at a's top, centred, not slid off
    assert xa[:, 1].max() - 0.01 < xb[:, 1].min() < xa[:, 1].max() + 0.005
    assert np.all((xb[:, [0, 2]] > -0.01) & (xb[:, [0, 2]] < 0.21))
    # penetration, measured independently: b's vertices inside a's deformed tet mesh
    assert penetration(xb, xa, model.tets.numpy()[: a.tet_count]) < 0.02 * 0.15
    assert penetration(xa, xb, model.tets.numpy()[top.tet_start :] - top.vertex_start) < 0.02 * 0.15
    assert deepest < 0.05 * 0.15  # the deepest contact over the whole run, impact included


def test_head_on_collision_conserves_momentum(device):
    b = ModelBuilder()
    add_body(b, "left", *_box((-0.35, 0, 0), (0.2, 0.2, 0.2), (2, 2, 2)), 2e5, 0.3, 1000.0, velocity=(2.0, 0.0, 0.0))
    add_body(
        b, "right", *_box((0.15, 0.02, 0.01), (0.2, 0.2, 0.2), (2, 2, 2)), 2e5, 0.3, 500.0, velocity=(-1.0, 0.0, 0.0)
    )
    model = b.finalize(device)
    solver = Solver(model, gravity=(0, 0, 0), ground=None, cg_iterations=300, cg_tolerance=1e-6)
    mass = model.mass.numpy()
    p0 = (mass[:, None] * model.initial_v.numpy()).sum(axis=0)
    contacts = []
    s = _run(solver, model, 120, 1 / 240, each=lambda _: contacts.append(solver.collider.read_stats()[0]))
    assert sum(contacts) > 0  # they did collide
    p1 = (mass[:, None] * s.v.numpy()).sum(axis=0)
    assert np.linalg.norm(p1 - p0) < 0.01 * np.abs(mass[:, None] * model.initial_v.numpy()).sum(axis=0)[0]
    v_left = s.v.numpy()[: model.bodies[0].vertex_count, 0].mean()
    v_right = s.v.numpy()[model.bodies[1].vertex_start :, 0].mean()
    assert v_left < v_right  # they bounced apart


@pytest.mark.parametrize("spacing", [0.0, 0.01])
def test_thin_bar_dropped_across_a_thin_bar(device, spacing):
    """Vertices only (the paper) miss two crossing bars; surface samples catch them.

    Nine cells along each 1 m bar put vertices at +-0.056 m from the crossing, outside the other bar's
    0.04 m width: no vertex ever enters the other bar, only the surfaces cross.
    """
    b = ModelBuilder()
    lower = _box((-0.5, 0.0, -0.02), (1.0, 0.04, 0.04), (9, 1, 1))
    upper = _box((-0.02, 0.1, -0.5), (0.04, 0.04, 1.0), (1, 1, 9))
    add_body(b, "lower", *lower, 1e7, 0.3, 1000.0, pinned=np.ones(len(lower[0]), bool))
    add_body(b, "upper", *upper, 1e7, 0.3, 1000.0, damping_stiffness=0.002, collision_spacing=spacing)
    model = b.finalize(device)
    solver = Solver(model, ground=None, cg_iterations=200, cg_tolerance=1e-5)
    x = _run(solver, model, 90, 1 / 240).x.numpy()
    up = model.bodies[1]
    xu = x[up.vertex_start :]
    if spacing == 0.0:
        assert xu[:, 1].max() < 0.0  # fell straight through the lower bar
        return
    near = np.abs(xu[:, 2]) < 0.1
    assert 0.04 - 0.002 < xu[near, 1].min() < 0.045  # resting on top at the crossing
    # the upper bar's bottom face, sampled finely, against the lower bar's tets
    bottom = np.flatnonzero(np.isclose(upper[0][:, 1], 0.1))
    t = np.linspace(0.0, 1.0, 41)
    edges = [(i, j) for i in bottom for j in bottom if i < j and np.linalg.norm(upper[0][i] - upper[0][j]) < 0.112]
    samples = np.concatenate([xu[i] + t[:, None] * (xu[j] - xu[i]) for i, j in edges])
    lower_tets = model.tets.numpy()[: model.bodies[0].tet_count]
    assert penetration(samples, x[: model.bodies[0].vertex_count], lower_tets) < 0.02 * 0.04


def test_self_collision_follows_the_scene(device):
    """Two blocks in ONE tet mesh: they collide only when the body collides with itself."""
    va, ta = _box((0, 0.0, 0), (0.2, 0.2, 0.2), (2, 2, 2))
    vb, tb = _box((0.02, 0.25, 0.02), (0.16, 0.16, 0.16), (2, 2, 2))
    vertices = np.concatenate([va, vb])
    tets = np.concatenate([ta, tb + len(va)])
    lows = []
    for self_collision in (False, True):
        b = ModelBuilder()
        add_body(
            b,
            "pair",
            vertices,
            tets,
            1e5,
            0.3,
            1000.0,
            self_collision=self_collision,
            pinned=np.arange(len(vertices)) < len(va),
        )
        model = b.finalize(device)
        solver = Solver(model, ground=None, cg_iterations=200, cg_tolerance=1e-5)
        assert (solver.collider is not None) == self_collision
        lows.append(_run(solver, model, 120, 1 / 240).x.numpy()[len(va) :, 1].min())
    assert lows[0] < 0.0  # passed through its own lower block
    assert lows[1] > 0.2 - 0.02 * 0.16  # rests on it


def test_a_body_at_rest_has_no_self_contacts(device):
    v, t = _box((0, 0, 0), (0.3, 0.1, 0.2), (3, 2, 2))
    b = ModelBuilder()
    add_body(b, "block", v, t, 1e5, 0.3, 1000.0, self_collision=True, collision_spacing=0.02)
    model = b.finalize(device)
    solver = Solver(model, gravity=(0, 0, 0), ground=None)
    x = _run(solver, model, 5, 1 / 240).x.numpy()
    total, most, depth, _ = solver.collider.read_stats()
    assert total == 0 and depth == 0.0
    np.testing.assert_allclose(x, v, atol=1e-5)


def _count_launches(monkeypatch, solver, model):
    """Kernel names launched by one step: direct launches plus replays of recorded ones (CG's)."""
    names = []
    real, real_tiled, replay = wp.launch, wp.launch_tiled, wp.Launch.launch

    def counting(kernel, *args, **kwargs):
        if not kwargs.get("record_cmd"):
            names.append(kernel.key)
        return real(kernel, *args, **kwargs)

    def counting_tiled(kernel, *args, **kwargs):
        names.append(kernel.key)
        return real_tiled(kernel, *args, **kwargs)

    def counting_replay(self, *args, **kwargs):
        names.append(self.kernel.key)
        return replay(self, *args, **kwargs)

    monkeypatch.setattr(wp, "launch", counting)
    monkeypatch.setattr(wp, "launch_tiled", counting_tiled)
    monkeypatch.setattr(wp.Launch, "launch", counting_replay)
    s0, s1 = model.state(), model.state()
    solver.step(s0, s1, 1 / 240)
    monkeypatch.setattr(wp, "launch", real)
    monkeypatch.setattr(wp.Launch, "launch", replay)
    return names


def test_only_scenes_that_collide_launch_collision_kernels(device, monkeypatch):
    collision_kernels = {
        "detect_contacts",
        "detect_contacts_direct",
        "contact_forces",
        "collision_points",
        "refit_trees",
    }
    detection = {"detect_contacts", "detect_contacts_direct"}  # through a BVH of the body boxes, or directly
    single = ModelBuilder()
    add_body(single, "one", *_box((0, 0.5, 0), (0.2, 0.2, 0.2), (2, 2, 2)), 1e5, 0.3, 1000.0)
    model = single.finalize(device)
    for mode in ("grid", "launches"):
        solver = Solver(model, cg_iterations=10, cg_tolerance=0.0)
        solver.cg = CGSolver(model.row_start, model.cols, model.free, 10, device, mode=mode)
        names = _count_launches(monkeypatch, solver, model)
        assert not collision_kernels & set(names)
        assert solver.grad.shape[0] == 0  # the elastic launch sums no rotated distance gradients either
        # the elastic part kept apart from the system (added in, with the preconditioner: 3 launches) and one
        # look at the tets' rotations, two launches (they did not turn: no second solve, no second look)
        assert names.count("turn_rotations") == 1 and names.count("replace_turned") == 1
        # one launch zeroes what the step accumulates into and counts in (instead of a memset each)
        assert names.count("clear_step") == 1
        updates = 3 + 2 + 1
        if mode == "grid":  # the whole solve is one launch after one reset
            solve = "cg_solve_held" if solver.cg.held else "cg_solve"  # held: every chunk has a thread (CUDA)
            assert names.count(solve) == 1 and names.count("cg_solve_reset") == 1
            assert len(names) <= 2 + 8 + updates
        else:
            # a fixed count of 10 CG iterations: 2 launches each (one product, one update), the loop checked
            # every 4 iterations (3 checks for 10), plus the fixed stages and the start (reset, A x, A d, the
            # line step, init, the first product, the loop test, finish), and the first late-contact pass's
            # one look at the vertices (it found nothing: no second solve, and no second pass)
            assert names.count("cg_update") == 12 and names.count("cg_advance") == 3
            assert names.count("cg_project") == 1 and names.count("cg_apply") == 12 + 3
            assert solver.contact_passes > 1 and names.count("late_vertex_contacts") == 1
            assert len(names) <= 2 * 12 + 3 + 12 + 1 + updates

    pair = ModelBuilder()
    add_body(pair, "one", *_box((0, 0.5, 0), (0.2, 0.2, 0.2), (2, 2, 2)), 1e5, 0.3, 1000.0)
    add_body(pair, "two", *_box((0, 0.9, 0), (0.2, 0.2, 0.2), (2, 2, 2)), 1e5, 0.3, 1000.0)
    model = pair.finalize(device)
    colliding = Solver(model, cg_iterations=10, cg_tolerance=0.0)
    launched = set(_count_launches(monkeypatch, colliding, model))
    assert collision_kernels - detection <= launched and len(launched & detection) == 1
    assert colliding.grad.shape[0] == model.vertex_count
    assert not collision_kernels & set(_count_launches(monkeypatch, Solver(model, collision=None), model))


def test_overlapped_captured_step_matches_a_serial_direct_one(device):
    """On CUDA the collision stage's preparation runs on a side stream beside the elastic launch, forked and
    joined inside the captured graph: from the same state, a replayed step prepares bit for bit what the
    phases run one after another prepare, finds the same contacts and lands where that step lands. No late
    passes: they prepare again at a solve's answer, which float atomics make differ in the last bits."""
    if not wp.get_device(device).is_cuda:
        pytest.skip("streams and graph capture need a CUDA device")
    b = ModelBuilder()
    add_body(b, "a", *_box((0, 0, 0), (0.2, 0.2, 0.2), (3, 3, 3)), 1e5, 0.3, 1000.0, damping_stiffness=0.01)
    add_body(b, "b", *_box((0.02, 0.21, 0.03), (0.15, 0.15, 0.15), (3, 3, 3)), 1e5, 0.3, 1000.0, velocity=(0, -2, 0))
    model = b.finalize(device)
    solver = Solver(model, ground=Ground(), cg_iterations=100, cg_tolerance=1e-6, contact_passes=0)
    c = solver.collider
    dt = 1 / 240
    start = _run(solver, model, 8, dt)  # b has landed on a: contacts in every step from here

    def prepared_and_found():
        n = int(c.count.numpy()[0])
        assert n > 0
        contacts = set(zip(c.contact_point.numpy()[:n].tolist(), c.contact_cell.numpy()[:n].tolist(), strict=True))
        buffers = [c.points, c.point_velocity, c.tet_inverse, c.tet_origin, c.node_lower, c.node_upper]
        return [a.numpy().copy() for a in buffers], contacts

    out = model.state()
    for _, phase in solver.phases(start, out, dt, overlap=False):
        phase()
    serial_buffers, serial_contacts = prepared_and_found()
    serial_x = out.x.numpy().copy()
    c.points.zero_()  # what the replay prepares must be its own
    c.tet_inverse.zero_()
    with wp.ScopedCapture(device=device) as capture:
        solver.step(start, out, dt)
    wp.capture_launch(capture.graph)
    buffers, contacts = prepared_and_found()
    for got, want in zip(buffers, serial_buffers, strict=True):
        np.testing.assert_array_equal(got, want)
    assert contacts == serial_contacts
    np.testing.assert_allclose(out.x.numpy(), serial_x, atol=1e-6)


def test_contact_buffer_overflow_is_reported(device):
    b = ModelBuilder()
    add_body(b, "a", *_box((0, 0, 0), (0.2, 0.2, 0.2), (2, 2, 2)), 1e5, 0.3, 1000.0)
    add_body(b, "b", *_box((0.0, 0.1, 0.0), (0.2, 0.2, 0.2), (2, 2, 2)), 1e5, 0.3, 1000.0, collision_spacing=0.01)
    model = b.finalize(device)
    solver = Solver(model, ground=None, collision=CollisionSettings(contacts_per_point=0.001))
    _run(solver, model, 1, 1 / 240)
    *_, overflow = solver.collider.read_stats()
    assert overflow


@pytest.mark.parametrize("stiffness", [1e4, 1e6, 1e8, 1e10])
def test_collision_penalty_across_orders_of_magnitude_stays_stable(device, stiffness):
    """The implicit penalty: soft to extremely stiff, no NaN and no energy beyond what the drop put in."""
    b = ModelBuilder()
    add_body(
        b, "a", *_box((0, 0, 0), (0.2, 0.2, 0.2), (2, 2, 2)), 1e5, 0.3, 1000.0, pinned=None, damping_stiffness=0.01
    )
    add_body(b, "b", *_box((0.02, 0.3, 0.02), (0.16, 0.16, 0.16), (2, 2, 2)), 1e5, 0.3, 1000.0, damping_stiffness=0.01)
    model = b.finalize(device)
    solver = Solver(
        model, ground=Ground(), cg_iterations=300, cg_tolerance=1e-5, collision=CollisionSettings(stiffness=stiffness)
    )
    mass = model.mass.numpy()
    drop = 9.81 * 0.3 * mass[model.bodies[1].vertex_start :].sum()  # J: the most the fall can give
    peak = [0.0]

    def kinetic(s):
        peak[0] = max(peak[0], 0.5 * float((mass[:, None] * s.v.numpy() ** 2).sum()))

    s = _run(solver, model, 240, 1 / 240, each=kinetic)
    assert solver.first_bad_vertex() is None and np.isfinite(s.x.numpy()).all()
    assert peak[0] < 1.05 * drop
    xb = s.x.numpy()[model.bodies[1].vertex_start :]
    assert xb[:, 1].mean() > 0.2  # still on top of a, not through it (a soft penalty lets it sink and tilt)


def _rotation(deg_x, deg_y):
    ax, ay = np.radians(deg_x), np.radians(deg_y)
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    return ry @ rx


def test_tet_trees_hold_every_tet_once_in_balanced_leaves():
    rng = np.random.default_rng(3)
    x = rng.random((400, 3))
    for n in [1, 5, 37, 200]:
        leaves = tet_tree(rng.integers(0, 400, size=(n, 4)), x)
        count = len(leaves)
        assert count & (count - 1) == 0 and count < max(2, 2 * -(-n // 4))  # a power of two, no spare level
        held = leaves[leaves >= 0]
        assert sorted(held) == list(range(n))  # every tet of the body, once
        assert (leaves >= 0).sum(axis=1).min() >= min(n, 1)  # no empty leaf: splits are even


def test_model_lays_the_bodies_trees_end_to_end():
    """Each body's leaves hold exactly its own (global) tets; its nodes are 2 L - 1, its leaves last."""
    b = ModelBuilder()
    for k, cells in enumerate([(1, 1, 1), (3, 2, 2), (4, 4, 3)]):
        add_body(b, f"b{k}", *_box((k, 0, 0), (0.2, 0.2, 0.2), cells), 1e5, 0.3, 1000.0)
    model = b.finalize("cpu")
    node_start, leaf_start = model.tree_node_start.numpy(), model.tree_leaf_start.numpy()
    leaf_tets = model.tree_leaf_tets.numpy()
    for k, body in enumerate(model.bodies):
        leaves = leaf_tets[leaf_start[k] : leaf_start[k + 1]]
        assert node_start[k + 1] - node_start[k] == 2 * len(leaves) - 1
        assert sorted(leaves[leaves >= 0]) == list(range(body.tet_start, body.tet_start + body.tet_count))


def test_tet_trees_refuse_a_body_deeper_than_the_walk_can_keep(monkeypatch):
    """The walk stacks 8 bits per three levels in an int64: a deeper tree is refused, naming the body's size."""
    import warpfem.prep.geometry as geometry

    rng = np.random.default_rng(4)
    x, tets = rng.random((40, 3)), rng.integers(0, 40, size=(33, 4))  # 9 leaves -> 16: a tree of 4 levels
    geometry.tet_tree(tets, x)
    monkeypatch.setattr(geometry, "MAX_TREE_LEVELS", 3)
    with pytest.raises(ValueError, match="a body of 33 tets needs a tree of 4 levels"):
        geometry.tet_tree(tets, x)


@pytest.mark.parametrize("bodies", ["direct", "bvh"])
@pytest.mark.parametrize("cells", [(1, 1, 1), (3, 4, 3), (5, 4, 5)])
@pytest.mark.parametrize("lanes", [1, 2, 4])
def test_detection_finds_exactly_the_points_inside_other_bodies(device, lanes, cells, bodies, monkeypatch):
    """Against a NumPy barycentric test of every collision point against every tet it may collide with.

    With the bodies' boxes tested directly (few bodies) and through a BVH of them (many: forced here).

    Two convex boxes, rotated and interpenetrating, a third body colliding with itself: two boxes of one
    mesh crossing each other (their points lie in each other's tets, far from their one-rings), which also
    crosses the others, and a lone tet (a tree of one leaf) inside the first box. Every body is convex, so a
    point inside one of its tets is below all its faces (a positive depth, which a contact needs). The box
    resolutions give trees of 1 to 9 levels below the root, so the walk's first step down takes 1, 2 and 3
    levels.
    """

    def box(offset, rx, ry):
        verts, tets = _box((-0.15, -0.15, -0.15), (0.3, 0.3, 0.3), cells)
        return verts @ _rotation(rx, ry).T + np.asarray(offset), tets

    b = ModelBuilder()
    for k, (offset, rx, ry) in enumerate([((0.0, 0.0, 0.0), 0, 0), ((0.15, 0.12, 0.05), 30, 40)]):
        add_body(b, f"b{k}", *box(offset, rx, ry), 1e5, 0.3, 1000.0, collision_spacing=0.04)
    (va, ta), (vb, tb) = box((-0.1, 0.2, 0.1), 10, 70), box((-0.05, 0.3, 0.0), 45, 0)
    verts, tets = np.concatenate([va, vb]), np.concatenate([ta, tb + len(va)])
    add_body(b, "crossed", verts, tets, 1e5, 0.3, 1000.0, collision_spacing=0.04, self_collision=True)
    lone = np.array([[-0.1, -0.1, -0.1], [0.1, -0.1, -0.1], [-0.1, 0.1, -0.1], [-0.1, -0.1, 0.1]])
    add_body(b, "tet", lone, np.array([[0, 1, 2, 3]]), 1e5, 0.3, 1000.0, collision_spacing=0.04)
    model = b.finalize(device)
    x = model.rest_x.numpy()
    monkeypatch.setattr("warpfem.sim.collision.DIRECT_BODIES", 16 if bodies == "direct" else 0)
    solver = Solver(model, ground=None)
    assert solver.collider.direct == (bodies == "direct")
    xs = wp.array(x, dtype=wp.vec3, device=device)
    v = wp.zeros_like(xs)
    rotation = wp.array(np.tile(np.eye(3), (model.tet_count, 1, 1)), dtype=wp.mat33, device=device)
    c = solver.collider
    c.lanes = lanes  # threads per point, each walking a share of the bodies whose boxes hold it
    c.rotate_gradients(rotation)
    c.prepare(xs, v)
    c.respond(xs, v, 1 / 240, wp.zeros_like(xs), wp.zeros_like(solver.matrix))
    n = int(c.count.numpy()[0])
    assert 0 < n <= c.capacity
    found = set(c.contact_point.numpy()[:n].tolist())
    contact_body = model.tet_body.numpy()[c.contact_cell.numpy()[:n]]
    pairs = list(zip(c.contact_point.numpy()[:n].tolist(), contact_body.tolist(), strict=True))
    assert len(pairs) == len(set(pairs))  # at most one contact per point and body

    points = c.points.numpy()
    point_body = model.point_body.numpy()
    anchors = model.point_anchor.numpy()
    tets = model.tets.numpy()
    tet_body = model.tet_body.numpy()
    inside = inside_tets(points, x, tets)  # (points, tets)
    row_start, cols = model.row_start.numpy(), model.cols.numpy()
    neighbours = [set(cols[row_start[i] : row_start[i + 1]]) for i in range(len(row_start) - 1)]

    def near(anchor, tet):  # the self-collision rule: an anchor in a corner's one-ring
        return any(a >= 0 and any(max(a, c) in neighbours[min(a, c)] for c in tet) for a in anchor)

    expected = set()
    self_body = model.body_self.numpy()
    for p in np.flatnonzero(inside.any(axis=1)):
        for e in np.flatnonzero(inside[p]):
            other = tet_body[e] != point_body[p]
            if other or (self_body[point_body[p]] and not near(anchors[p], tets[e])):
                expected.add(int(p))
                break
    assert found == expected
    contact_tets, contact_points = c.contact_cell.numpy()[:n], c.contact_point.numpy()[:n]
    assert np.any((tet_body[contact_tets] == 2) & (point_body[contact_points] == 2))  # self contacts were tested


def _inside_other_body(model, x, points):
    """Per point (at ``points``), whether a tet of another body (vertices ``x``) holds it: NumPy barycentrics."""
    tet_body, point_body = model.tet_body.numpy(), model.point_body.numpy()
    inside = inside_tets(points, x, model.tets.numpy(), tol=1e-6)
    return (inside & (tet_body[None, :] != point_body[:, None])).any(axis=1)


def _pairs_inside_other_body(model, x, points):
    """The (point, body) pairs where a tet of a body other than the point's (vertices ``x``) holds the point."""
    tet_body, point_body = model.tet_body.numpy(), model.point_body.numpy()
    inside = inside_tets(points, x, model.tets.numpy(), tol=1e-6) & (tet_body[None, :] != point_body[:, None])
    return {(int(p), int(tet_body[e])) for p, e in zip(*np.nonzero(inside), strict=True)}


@pytest.mark.parametrize("bodies", ["direct", "bvh", "carried"])
@pytest.mark.parametrize("speed, gap", [(0.2, 0.0005), (8.0, 0.01)])
def test_a_late_pass_finds_every_point_the_step_carried_into_another_body(device, bodies, speed, gap, monkeypatch):
    """Against NumPy: a late pass at a step's end positions finds exactly the collision points then inside another
    body's tets that had no contact at the step's start, and asks for a second solve for those that end the step
    deeper than the collider's ``solve_depth`` (half the contact offset) alone.

    Two boxes overlapping at the start (contacts there), a third closing on both at ``speed`` (m/s) from ``gap``
    (m) away, within the step's travel: slowly from half a millimetre (it grazes them, 0.33 mm deep), fast from a
    centimetre (23 mm). Each of its vertices' velocities carries a little noise of its own, least along the
    approach. A late contact's depth is how far its point passed the face it came in through.

    In a scene that carries its contacts (``carried``), whose late look is its only look at every point, it
    finds the (point, body) pairs instead: a point touching one body at the start is found inside another.
    """
    monkeypatch.setattr("warpfem.sim.collision.DIRECT_BODIES", 16 if bodies == "direct" else 0)
    monkeypatch.setattr("warpfem.sim.collision.CARRY_BODIES", 0 if bodies == "carried" else 64)
    dt = 1 / 240
    b = ModelBuilder()
    for k, lo in enumerate([(0.0, 0.0, 0.0), (-0.005, 0.29, 0.02), (0.3 + gap, 0.01, 0.03)]):
        add_body(b, f"b{k}", *_box(lo, (0.3, 0.3, 0.3), (3, 3, 3)), 1e5, 0.3, 1000.0, collision_spacing=0.03)
    model = b.finalize(device)
    solver = Solver(model, ground=None)
    c = solver.collider
    assert c.direct == (bodies == "direct") and c.carries == (bodies == "carried")
    x0 = model.rest_x.numpy()
    body = model.vertex_body.numpy()
    v = np.random.default_rng(5).normal(scale=0.01 * speed, size=x0.shape)  # no point on another's tet face
    v[:, 0] = 0.001 * v[:, 0] - speed  # along x: 0.03 mm of noise at most over the step
    v = np.where((body == 2)[:, None], v, 0.0).astype(np.float32)  # the first two keep still
    x1 = (x0 + dt * v).astype(np.float32)
    xs0, xs1, vs = (wp.array(a, dtype=wp.vec3, device=device) for a in (x0, x1, v))
    c.rotate_gradients(wp.array(np.tile(np.eye(3), (model.tet_count, 1, 1)), dtype=wp.mat33, device=device))
    c.prepare(xs0, vs)
    c.respond(xs0, vs, dt, wp.zeros_like(xs0), wp.zeros_like(solver.matrix))
    start = int(c.count.numpy()[0])
    at_start = set(c.contact_point.numpy()[:start].tolist())
    start_bodies = model.tet_body.numpy()[c.contact_cell.numpy()[:start]]
    start_pairs = set(zip(c.contact_point.numpy()[:start].tolist(), start_bodies.tolist(), strict=True))
    assert at_start  # the first two boxes overlap
    count = wp.zeros(1, dtype=wp.int32, device=device)
    c.respond_late(xs1, vs, dt, wp.zeros_like(xs0), wp.zeros_like(solver.matrix), count)
    end = int(c.count.numpy()[0])
    late = c.contact_point.numpy()[start:end]
    other = model.tet_body.numpy()[c.contact_cell.numpy()[start:end]]
    pairs = set(zip(late.tolist(), other.tolist(), strict=True))
    assert len(pairs) == len(late)  # at most one contact per point and body

    cells, bary = model.cells.numpy()[model.point_cell.numpy()], model.point_bary.numpy()
    points = np.einsum("pk,pkj->pj", bary, x1[cells])
    if bodies == "carried":
        touching = {p for p in at_start if sum(q == p for q, _ in start_pairs) > 1}
        expected_pairs = _pairs_inside_other_body(model, x1, points) - start_pairs
        expected_pairs = {(p, o) for p, o in expected_pairs if p not in touching}
        assert pairs == expected_pairs
        if speed > 1.0:  # a point touching one body was found inside another
            assert {p for p, _ in pairs} & at_start
    else:
        inside = _inside_other_body(model, x1, points)
        expected = set(np.flatnonzero(inside).tolist()) - at_start
        assert expected  # the third box's face crossed into the first
        assert set(late.tolist()) == expected
    point_body = model.point_body.numpy()[late]
    front = 0.3 + gap - speed * dt  # the third box's face that closes on the others, at the step's end
    depth = np.where(point_body == 2, np.where(other == 0, 0.3, 0.295) - points[late, 0], points[late, 0] - front)
    solves = int(count.numpy()[0])
    tol = 5e-5  # the noise along x
    assert int((depth > c.solve_depth + tol).sum()) <= solves <= int((depth > c.solve_depth - tol).sum())
    assert (solves > 0) == (speed > 1.0)  # the grazing contacts ask for no second solve


@pytest.mark.parametrize("bodies", ["direct", "bvh"])
@pytest.mark.parametrize("gap", [0.0021, 0.0113, 0.0307])
def test_a_late_pass_misses_no_point_between_bodies_that_both_move_and_turn(device, bodies, gap, monkeypatch):
    """Against NumPy: where both bodies move and spin, a late pass still finds every collision point that the
    step carried into the other body (none was inside at the start).

    Two boxes ``gap`` (m) apart close on each other at 1 m/s each and spin at up to 20 rad/s about axes of
    their own, so their corners swing up to about 5 m/s, 2 cm in the step: the late pass must find exactly
    what NumPy's barycentrics find at the step's end, whichever body's motion carried a point in.
    """
    monkeypatch.setattr("warpfem.sim.collision.DIRECT_BODIES", 16 if bodies == "direct" else 0)
    dt = 1 / 240
    b = ModelBuilder()
    for k, lo in enumerate([(0.0, 0.0, 0.0), (0.3 + gap, 0.0517, 0.0231)]):
        add_body(b, f"b{k}", *_box(lo, (0.3, 0.3, 0.3), (3, 3, 3)), 1e5, 0.3, 1000.0, collision_spacing=0.02)
    model = b.finalize(device)
    solver = Solver(model, ground=None)
    c = solver.collider
    x0 = model.rest_x.numpy()
    body = model.vertex_body.numpy()
    centre = np.array([x0[body == k].mean(axis=0) for k in range(2)])[body]
    spin = np.where((body == 0)[:, None], [0.0, 20.0, 5.0], [3.0, -4.0, 20.0])
    v = np.cross(spin, x0 - centre) + np.where((body == 0)[:, None], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0])
    v = v.astype(np.float32)
    x1 = (x0 + dt * v).astype(np.float32)
    xs0, xs1, vs = (wp.array(a, dtype=wp.vec3, device=device) for a in (x0, x1, v))
    c.rotate_gradients(wp.array(np.tile(np.eye(3), (model.tet_count, 1, 1)), dtype=wp.mat33, device=device))
    c.prepare(xs0, vs)
    c.respond(xs0, vs, dt, wp.zeros_like(xs0), wp.zeros_like(solver.matrix))
    assert int(c.count.numpy()[0]) == 0
    count = wp.zeros(1, dtype=wp.int32, device=device)
    c.respond_late(xs1, vs, dt, wp.zeros_like(xs0), wp.zeros_like(solver.matrix), count)
    late = set(c.contact_point.numpy()[: int(c.count.numpy()[0])].tolist())

    cells, bary = model.cells.numpy()[model.point_cell.numpy()], model.point_bary.numpy()
    points = np.einsum("pk,pkj->pj", bary, x1[cells])
    expected = set(np.flatnonzero(_inside_other_body(model, x1, points)).tolist())
    assert expected or gap > 0.003
    assert late == expected


def test_top_speed_per_body_matches_numpy(device):
    """``read_speeds``: per body, the fastest collision point (its velocity interpolated like its position),
    against NumPy. Three bodies of a few hundred points each (whole warps of one body, and warps that straddle
    two), spinning at different rates so that every point has its own speed."""
    b = ModelBuilder()
    for k in range(3):
        mesh = _box((0.4 * k, 0, 0), (0.3, 0.3, 0.3), (3, 3, 3))
        add_body(b, f"b{k}", *mesh, 1e5, 0.3, 1000.0, collision_spacing=0.05)
    model = b.finalize(device)
    solver = Solver(model, ground=None)
    c = solver.collider
    x = model.rest_x.numpy()
    rng = np.random.default_rng(4)
    v = rng.normal(size=x.shape) * np.repeat([1.0, 3.0, 0.5], [body.vertex_count for body in model.bodies])[:, None]
    xs = wp.array(x, dtype=wp.vec3, device=device)
    vs = wp.array(v.astype(np.float32), dtype=wp.vec3, device=device)
    c.rotate_gradients(wp.array(np.tile(np.eye(3), (model.tet_count, 1, 1)), dtype=wp.mat33, device=device))
    c.prepare(xs, vs)
    c.respond(xs, vs, 1 / 240, wp.zeros_like(xs), wp.zeros_like(solver.matrix))
    tets = model.cells.numpy()[model.point_cell.numpy()]
    bary = model.point_bary.numpy()
    speed = np.linalg.norm(np.einsum("pk,pkj->pj", bary, v[tets]), axis=1)
    body = model.point_body.numpy()
    assert np.bincount(body).min() > 64  # more than a warp of points per body
    expected = np.array([speed[body == k].max() for k in range(3)])
    np.testing.assert_allclose(c.read_speeds(), expected, rtol=1e-5)
    assert not c.read_speeds().any()  # reset by the read


def test_detection_shares_points_among_lanes_only_where_they_leave_the_device_idle():
    """Up to four threads a collision point while the points number under 1024 per SM; one where they fill it."""
    from warpfem.sim.collision import detect_lanes

    h200 = type("Device", (), {"is_cuda": True, "sm_count": 132})()
    assert [detect_lanes(n, h200) for n in (1, 22_464, 36_916, 67_584, 89_856, 1_437_696)] == [4, 4, 3, 2, 1, 1]
    assert detect_lanes(22_464, wp.get_device("cpu")) == 1


_finalize = ModelBuilder.finalize


def _bunnies(ordered: bool, elements: str, monkeypatch) -> warpfem.Simulation:
    """Two overlapping bunnies (400 faces), their model stored in space order or not."""
    monkeypatch.setattr(ModelBuilder, "finalize", functools.partialmethod(_finalize, ordered=ordered))
    bunny = {"mesh": "builtin:bunny", "subdivide": 0, "faces": 400, "scale": 0.5}
    doc = {
        "scene": {"frames": 1},
        "solver": {"elements": elements},
        "object": [
            {**bunny, "name": "a", "translate": [0.0, 0.5, 0.0]},
            {**bunny, "name": "b", "translate": [0.12, 0.6, 0.05], "rotate": [0.0, 60.0, 0.0]},
        ],
    }
    return warpfem.Simulation(warpfem.Scene.from_dict(doc, name="bunnies"), device="cpu")


@pytest.mark.parametrize("elements", ["linear", "quadratic"])
def test_points_in_space_order_are_the_same_points_near_each_other(elements, monkeypatch):
    """A model in space order (the default on CUDA for more than 16 bodies) holds each body's collision and skin
    points unchanged (rest position, anchors, mass), only reordered within the body; consecutive points lie at a
    quarter of the distance apart or less; and at the rest pose detection finds the same points inside the other
    body. With quadratic tets the points lie in their sub-tets, whose nodes give their positions."""

    def rows(model, prefix, extra):
        cells = model.cells.numpy()[getattr(model, f"{prefix}_cell").numpy()]
        bary = getattr(model, f"{prefix}_bary").numpy()
        x = np.einsum("pk,pkj->pj", bary, model.rest_x.numpy()[cells])
        cols = [x] + [getattr(model, f"{prefix}_{k}").numpy().reshape(len(x), -1) for k in extra]
        return x, np.round(np.hstack(cols).astype(np.float64), 6)

    def inside(sim):
        c = sim.solver.collider
        m = sim.model
        c.rotate_gradients(wp.array(np.tile(np.eye(3), (m.tet_count, 1, 1)), dtype=wp.mat33, device="cpu"))
        c.prepare(m.rest_x, m.initial_v)
        c.respond(m.rest_x, m.initial_v, 1 / 240, wp.zeros_like(m.rest_x), wp.zeros_like(sim.solver.matrix))
        n = int(c.count.numpy()[0])
        found = c.points.numpy()[c.contact_point.numpy()[:n]]
        return np.unique(np.round(found.astype(np.float64), 5), axis=0)

    plain, ordered = _bunnies(False, elements, monkeypatch), _bunnies(True, elements, monkeypatch)
    a, b = plain.model, ordered.model
    assert np.array_equal(a.point_body.numpy(), b.point_body.numpy())
    for prefix, extra in (("point", ("anchor", "mass", "body")), ("skin", ("mass",))):
        (xa, ra), (xb, rb) = rows(a, prefix, extra), rows(b, prefix, extra)
        assert len(ra) > 1000
        assert np.array_equal(np.unique(ra, axis=0), np.unique(rb, axis=0)), prefix
        step_a = np.linalg.norm(np.diff(xa, axis=0), axis=1).mean()
        step_b = np.linalg.norm(np.diff(xb, axis=0), axis=1).mean()
        assert step_b < 0.25 * step_a, (prefix, step_a, step_b)
    found = inside(plain)
    assert len(found) > 10 and np.array_equal(found, inside(ordered))


BAD_SETTINGS = [("stiffness", 0.0), ("friction", -0.1), ("offset", -0.001), ("offset", 0.05), ("offset", float("nan"))]


@pytest.mark.parametrize("field, value", BAD_SETTINGS)
def test_collision_settings_refuse_values_out_of_range(field, value):
    """A bad setting is refused where it is made, naming the field, before any solver is built on it."""
    with pytest.raises(ValueError, match=f"CollisionSettings.{field} must be"):
        CollisionSettings(**{field: value})


def test_a_carried_look_finds_the_full_looks_contacts_of_the_pairs_it_kept(device, monkeypatch):
    """A scene of many bodies starts a step from the step before's contacts: each kept (point, body) pair walked
    again where the points now lie. After the bodies move, it finds exactly the contacts a look at every point
    finds for those pairs, with the same cells, weights and depths, and none of the pairs it did not keep."""
    monkeypatch.setattr("warpfem.sim.collision.DIRECT_BODIES", 0)
    monkeypatch.setattr("warpfem.sim.collision.CARRY_BODIES", 0)
    b = ModelBuilder()
    for k, (offset, rx, ry) in enumerate([((0.0, 0.0, 0.0), 0, 0), ((0.15, 0.12, 0.05), 30, 40)]):
        verts, tets = _box((-0.15, -0.15, -0.15), (0.3, 0.3, 0.3), (3, 4, 3))
        add_body(b, f"b{k}", verts @ _rotation(rx, ry).T + np.asarray(offset), tets, 1e5, 0.3, 1000.0,
                 collision_spacing=0.04)  # fmt: skip
    model = b.finalize(device)
    solver = Solver(model, ground=None)
    c = solver.collider
    assert c.carries
    c.rotate_gradients(wp.array(np.tile(np.eye(3), (model.tet_count, 1, 1)), dtype=wp.mat33, device=device))
    tet_body = model.tet_body.numpy()

    def look(x: np.ndarray, carried: bool) -> dict:
        xs = wp.array(x, dtype=wp.vec3, device=device)
        v = wp.zeros_like(xs)
        c.prepare(xs, v)
        c.respond(xs, v, 1 / 240, wp.zeros_like(xs), wp.zeros_like(solver.matrix), carried=carried)
        n = int(c.count.numpy()[0])
        point, cell = c.contact_point.numpy()[:n].copy(), c.contact_cell.numpy()[:n].copy()  # views on the CPU
        rows = zip(point, cell, c.contact_bary.numpy()[:n].copy(), c.contact_depth.numpy()[:n].copy(), strict=True)
        return {(int(p), int(tet_body[e])): (int(e), w, d) for p, e, w, d in rows}

    x = model.rest_x.numpy()
    kept = look(x, carried=False)
    c.keep()
    moved = x.copy()
    second = np.unique(model.tets.numpy()[tet_body == 1])
    moved[second] += np.array([-0.02, -0.01, 0.015])  # the second box further in
    full = look(moved, carried=False)
    carried = look(moved, carried=True)
    assert kept and set(full) - set(kept)  # moving in made pairs the step before did not have
    assert set(carried) == set(full) & set(kept)
    for pair, (e, w, d) in carried.items():
        assert full[pair][0] == e
        np.testing.assert_allclose(full[pair][1], w, atol=1e-6)
        assert full[pair][2] == pytest.approx(d, abs=1e-7)


def test_collision_point_normals_of_the_wrong_count_are_an_input_error():
    """A body's geometry with a normal row per collision point is taken; with another count the model refuses
    it, naming the body, rather than lifting the points along the wrong normals."""
    import dataclasses

    from warpfem.errors import InputError
    from warpfem.prep.geometry import body_geometry

    V, T = box_tet_mesh((0, 0, 0), (0.3, 0.2, 0.1), (3, 2, 1))
    geometry = body_geometry(V, T, 0.0)
    assert geometry.point_normal.shape == (len(geometry.point_tet), 3) and not geometry.point_normal.any()
    builder = ModelBuilder()
    builder.add_body("a", V, T, geometry, 1e7, 0.3, 1000.0)
    wrong = dataclasses.replace(geometry, point_normal=np.ones((len(geometry.point_tet) - 1, 3)))
    with pytest.raises(InputError, match="body 'b': point_normal has"):
        builder.add_body("b", V + 1.0, T, wrong, 1e7, 0.3, 1000.0)


def test_a_scene_that_tests_every_body_box_itself_never_carries(device, monkeypatch):
    """A carried start needs a late look by pairs, which only detection through the body BVH has: a scene few
    enough for the direct detection looks at every point at each step's start, whatever the carrying threshold."""
    monkeypatch.setattr("warpfem.sim.collision.CARRY_BODIES", 0)
    b = ModelBuilder()
    for k in range(2):
        add_body(b, f"b{k}", *_box((0.4 * k, 0.0, 0.0), (0.3, 0.3, 0.3), (2, 2, 2)), 1e5, 0.3, 1000.0)
    model = b.finalize(device)
    for direct, carries in ((16, False), (0, True)):
        monkeypatch.setattr("warpfem.sim.collision.DIRECT_BODIES", direct)
        c = Solver(model, ground=None).collider
        assert c.direct == (direct > 0) and c.carries == carries

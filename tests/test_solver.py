"""Whole steps of the solver against analytic mechanics."""

import numpy as np
import pytest
import warp as wp

from warpfem.build import add_body
from warpfem.prep.shapes import box_tet_mesh
from warpfem.sim.integrate import Box, MeshCollider, Sphere
from warpfem.sim.model import ModelBuilder
from warpfem.sim.solver import DEFAULT_CONTACT_PASSES, Ground, Solver

G = 9.81


def _cube(device, y0=1.0, young=1e5, **kw):
    V, T = box_tet_mesh((0, y0, 0), (0.2, y0 + 0.2, 0.2), (2, 2, 2))
    b = ModelBuilder()
    add_body(b, "cube", V, T, young, 0.3, 1000.0, **kw)
    return b.finalize(device), V


def _run(solver, model, steps, dt):
    s0, s1 = model.state(), model.state()
    for _ in range(steps):
        solver.step(s0, s1, dt)
        s0, s1 = s1, s0
    return s0


def test_free_fall_matches_kinematics(device):
    model, V = _cube(device, y0=10.0)
    solver = Solver(model, gravity=(0, -G, 0), ground=None, cg_iterations=50, cg_tolerance=1e-6)
    dt, n = 1 / 240, 120
    x = _run(solver, model, n, dt).x.numpy()
    drop = V[:, 1].mean() - x[:, 1].mean()
    # backward Euler's exact discrete drop, and the analytic g t^2 / 2 within its O(dt) error
    assert drop == pytest.approx(G * dt * dt * n * (n + 1) / 2, rel=1e-4)
    assert drop == pytest.approx(G * (n * dt) ** 2 / 2, rel=0.01)
    np.testing.assert_allclose(x[:, [0, 2]], V[:, [0, 2]], atol=1e-5)  # no sideways drift, no deformation
    assert np.ptp(x[:, 1] - V[:, 1]) < 1e-5


def test_cg_starts_from_the_last_velocity_change(device):
    """CG starts from v moved along dv (the velocity change of the step that made the state): in a free fall
    that is nearly the answer, so a step from a state with its dv takes fewer iterations than from the same
    state with dv zeroed, and lands on the same velocities."""
    model, _ = _cube(device, y0=10.0)
    solver = Solver(model, gravity=(0, -G, 0), ground=None, cg_iterations=50, cg_tolerance=1e-4)
    s0, s1 = model.state(), model.state()
    solver.step(s0, s1, 1 / 240)
    np.testing.assert_array_equal(s1.dv.numpy(), s1.v.numpy() - s0.v.numpy())
    solver.read_cg_stats()
    iterations, v = [], []
    for zero_dv in (False, True):
        start = model.state()
        start.assign(s1)
        if zero_dv:
            start.dv.zero_()
        out = model.state()
        solver.step(start, out, 1 / 240)
        stats = solver.read_cg_stats()
        assert stats.residual_max < 1e-4
        iterations.append(stats.iterations)
        v.append(out.v.numpy())
    assert iterations[0] < iterations[1]
    np.testing.assert_allclose(v[0], v[1], atol=1e-4 * G / 240 * 10)


def test_cube_comes_to_rest_on_the_ground(device):
    model, V = _cube(device, y0=0.5, damping_stiffness=0.01)
    solver = Solver(model, ground=Ground(stiffness=1e6), cg_iterations=100, cg_tolerance=1e-5)
    s = _run(solver, model, 480, 1 / 240)
    x, v = s.x.numpy(), s.v.numpy()
    assert solver.first_bad_vertex() is None
    assert x[:, 1].min() > -0.002 * 0.2  # penetration below 0.2 % of the size
    assert x[:, 1].min() < 0.001  # it did land
    assert np.abs(v).max() < 0.05
    height = x[:, 1].max() - x[:, 1].min()
    assert height == pytest.approx(0.2, rel=0.02)  # elastic, only slightly compressed


def test_clamped_cantilever_sags_like_euler_bernoulli(device):
    L, h, E, rho = 1.0, 0.1, 1e8, 1000.0
    V, T = box_tet_mesh((0, 0, 0), (L, h, h), (50, 8, 8))  # linear tets lock in bending: 8 across
    b = ModelBuilder()
    add_body(b, "beam", V, T, E, 0.0, rho, pinned=V[:, 0] < 1e-9)
    model = b.finalize(device)
    solver = Solver(model, ground=None, cg_iterations=5000, cg_tolerance=1e-7)
    # backward Euler with a long step is a (damped) static solve: x1 = x0 + (M/dt^2 + K)^-1 M g
    x = _run(solver, model, 4, 100.0).x.numpy()
    tip = np.isclose(V[:, 0], L)
    sag = V[tip, 1].mean() - x[tip, 1].mean()
    w = rho * G * h * h
    euler_bernoulli = w * L**4 / (8 * E * h**4 / 12)
    assert sag == pytest.approx(euler_bernoulli, rel=0.10)


def test_pinned_vertices_do_not_move(device):
    V, T = box_tet_mesh((0, 1, 0), (0.2, 1.2, 0.2), (2, 2, 2))
    pinned = V[:, 1] > 1.2 - 1e-9
    b = ModelBuilder()
    add_body(b, "hang", V, T, 1e5, 0.3, 1000.0, pinned=pinned)
    model = b.finalize(device)
    x = _run(Solver(model, ground=None), model, 60, 1 / 120).x.numpy()
    np.testing.assert_array_equal(x[pinned], V[pinned].astype(np.float32))
    assert x[~pinned, 1].mean() < V[~pinned, 1].mean() - 1e-4  # the rest hangs down


def test_bodies_in_one_model_match_separate_runs(device):
    Va, Ta = box_tet_mesh((0, 0.3, 0), (0.2, 0.5, 0.2), (2, 2, 2))
    Vb, Tb = box_tet_mesh((1, 0.6, 0), (1.3, 0.7, 0.1), (3, 1, 1))
    params = [("a", Va, Ta, 1e5, 0.3, 1000.0), ("b", Vb, Tb, 3e5, 0.4, 500.0)]
    together = ModelBuilder()
    for p in params:
        add_body(together, *p, velocity=(0.5, 0, 0))
    model = together.finalize(device)
    cfg = dict(ground=Ground(), cg_iterations=200, cg_tolerance=1e-7)
    joint = _run(Solver(model, **cfg), model, 60, 1 / 120).x.numpy()
    for body, p in zip(model.bodies, params, strict=True):
        alone = ModelBuilder()
        add_body(alone, *p, velocity=(0.5, 0, 0))
        m = alone.finalize(device)
        x = _run(Solver(m, **cfg), m, 60, 1 / 120).x.numpy()
        np.testing.assert_allclose(joint[body.vertex_start : body.vertex_start + body.vertex_count], x, atol=2e-4)


def test_nan_is_flagged_with_its_vertex(device):
    model, V = _cube(device)
    solver = Solver(model)
    s0, s1 = model.state(), model.state()
    v = s0.v.numpy()
    v[7] = np.nan
    s0.v.assign(v)
    solver.step(s0, s1, 1 / 60)
    assert solver.first_bad_vertex() is not None
    assert solver.first_bad_vertex() is None  # the flag resets after reading


def test_captured_frame_replays_like_direct_execution(device):
    if not wp.get_device(device).is_cuda:
        pytest.skip("CUDA graph capture needs a CUDA device")
    model, _ = _cube(device, y0=0.3, damping_stiffness=0.01)
    solver = Solver(model, cg_iterations=60, cg_tolerance=1e-5)
    direct = _run(solver, model, 40, 1 / 240).x.numpy()
    s0, s1 = model.state(), model.state()
    with wp.ScopedCapture(device=device) as capture:
        solver.step(s0, s1, 1 / 240)
        solver.step(s1, s0, 1 / 240)
    for _ in range(20):
        wp.capture_launch(capture.graph)
    np.testing.assert_allclose(s0.x.numpy(), direct, atol=1e-5)


def test_drop_from_two_metres_stays_above_the_ground(device):
    model, V = _cube(device, y0=2.0, young=1e6, damping_stiffness=0.01)
    solver = Solver(model, ground=Ground(), cg_iterations=200, cg_tolerance=1e-5)
    s0, s1 = model.state(), model.state()
    lowest = np.inf
    for _ in range(240):  # 1 s: it lands at 6.3 m/s after 0.64 s
        solver.step(s0, s1, 1 / 240)
        s0, s1 = s1, s0
        lowest = min(lowest, s0.x.numpy()[:, 1].min())
    assert solver.first_bad_vertex() is None
    assert -0.02 * 0.2 < lowest < 0.001


@pytest.mark.parametrize("shape", ["sphere", "box"])
def test_cube_rests_on_a_static_obstacle(device, shape):
    model, V = _cube(device, y0=0.6, young=1e6, damping_stiffness=0.01)
    obstacle = Sphere((0.1, 0.0, 0.1), 0.5) if shape == "sphere" else Box((0.1, 0.25, 0.1), (0.3, 0.25, 0.3))
    solver = Solver(model, ground=None, obstacles=[obstacle], cg_iterations=200, cg_tolerance=1e-5)
    x = _run(solver, model, 240, 1 / 240).x.numpy()
    if shape == "sphere":
        clearance = np.linalg.norm(x - np.array([0.1, 0.0, 0.1]), axis=1) - 0.5
    else:
        clearance = x[:, 1] - 0.5  # the box's top face
    assert clearance.min() > -0.02 * 0.2  # not inside it
    assert clearance.min() < 0.002  # resting on it, not floating
    assert x[:, 1].min() > 0.3  # held up (without it the cube falls 1.2 m in this time)


def test_cg_path_reaches_the_solver(device):
    """``cg_path`` picks CG's path and, as "grid:B", its block count (one thread on the CPU)."""
    model, _ = _cube(device, y0=0.5, damping_stiffness=0.01)
    grid = Solver(model, cg_path="grid:3").cg
    assert grid.mode == "grid" and grid.grid_blocks == (3 if wp.get_device(device).is_cuda else 1)
    assert Solver(model, cg_path="launches").cg.mode == "launches"
    with pytest.raises(ValueError, match="mode"):
        Solver(model, cg_path="fast")
    for bad in ("grid:x", "launches:3"):  # a block count only for grid, and only digits
        with pytest.raises(ValueError, match="cg_path"):
            Solver(model, cg_path=bad)
    with pytest.raises(ValueError, match="grid_blocks"):
        Solver(model, cg_path="grid:0")


def test_a_body_landing_fast_stays_within_a_fraction_of_a_step_of_the_ground(device):
    """Vertices dragged down by their falling body are caught before they cross the ground, not a step late.

    A tilted cube lands at 5 m/s at 4 steps per 1/60 s frame (21 mm a step); its deepest vertex below the
    ground over the landing is measured on the positions (NumPy) against a third of one step's travel.
    """
    from warpfem.build import euler_rotation
    from warpfem.sim.solver import Ground
    from warpfem.simulation import Simulation

    V, T = box_tet_mesh((-0.15, -0.15, -0.15), (0.3, 0.3, 0.3), (3, 3, 3))
    V = V @ euler_rotation((25.0, 0.0, 35.0)).T + [0.0, 0.35, 0.0]
    b = ModelBuilder()
    add_body(b, "cube", V, T, 1e6, 0.3, 1000.0, velocity=(0.0, -5.0, 0.0), damping_stiffness=0.005)
    model = b.finalize(device)
    solver = Solver(model, ground=Ground(), collision=None, cg_iterations=200, cg_tolerance=1e-5)
    sim = Simulation.from_model(model, solver, substeps=4, fps=60.0)
    deepest = 0.0
    for _ in range(30):
        sim.step_frame()
        deepest = max(deepest, -float(sim.state().x.numpy()[:, 1].min()))
    assert deepest < 5.0 / 240.0 / 3.0, deepest


def test_the_visible_surface_rests_on_the_ground_where_it_bulges_out_of_the_tets(device):
    """A dense sphere around a coarse cube pokes 20 mm out of each face.

    Its lowest point (NumPy, on the mapped dense mesh) must stay on the ground, not 20 mm under it with the
    cube's face on the ground.
    """
    import trimesh

    from warpfem.prep.embedding import embed
    from warpfem.prep.tetmesh import boundary_faces
    from warpfem.simulation import Simulation

    V, T = box_tet_mesh((-0.15, -0.15, -0.15), (0.3, 0.3, 0.3), (3, 3, 3))
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.17)
    dense = np.asarray(sphere.vertices)
    lift = np.array([0.0, 0.25, 0.0])
    tet, bary = embed(dense, V, T, boundary_faces(T))
    b = ModelBuilder()
    add_body(
        b,
        "ball",
        V + lift,
        T,
        1e6,
        0.3,
        1000.0,
        damping_mass=2.0,
        embed_tet=tet,
        embed_bary=bary,
        dense_faces=np.asarray(sphere.faces),
    )
    model = b.finalize(device)
    solver = Solver(model, ground=Ground(), collision=None, cg_iterations=200, cg_tolerance=1e-5)
    sim = Simulation.from_model(model, solver, substeps=4, fps=60.0)
    lowest = []
    for _ in range(90):
        sim.step_frame()
        lowest.append(float(sim.dense_points("ball")[:, 1].min()))
    assert min(lowest) > -0.005, min(lowest)  # through the landing: within 5 mm (a quarter of the bulge)
    assert lowest[-1] > -0.001, lowest[-1]  # at rest: within 1 mm of the ground


def test_late_contact_passes_only_where_something_can_be_touched(device):
    """``contact_passes`` is kept where a static collider or contacts exist, 0 for a lone body in empty space
    (it pays nothing for them), and a negative count is refused."""
    model, _ = _cube(device, y0=0.5)
    assert (
        Solver(model).contact_passes == DEFAULT_CONTACT_PASSES and Solver(model, contact_passes=2).contact_passes == 2
    )
    assert Solver(model, ground=None).contact_passes == 0
    with pytest.raises(ValueError, match="contact_passes"):
        Solver(model, contact_passes=-1)


def test_late_passes_and_rotation_updates_can_be_lowered_after_construction_not_raised(device):
    """Each pass and update has its condition's slot allocated at construction: a count set later may drop to
    0 and come back, but not exceed what was allocated nor go negative (a one-line ValueError)."""
    model, _ = _cube(device, y0=0.5)
    solver = Solver(model, contact_passes=2, rotation_updates=2)
    solver.contact_passes, solver.rotation_updates = 0, 1
    assert (solver.contact_passes, solver.rotation_updates) == (0, 1)
    solver.contact_passes = 2
    for name, value in (("contact_passes", 3), ("rotation_updates", 3), ("contact_passes", -1)):
        with pytest.raises(ValueError, match=f"{name} can be lowered after construction, to 0-2, not set to {value}"):
            setattr(solver, name, value)
    assert (solver.contact_passes, solver.rotation_updates) == (2, 1)
    assert np.isfinite(_run(solver, model, 4, 1 / 240).x.numpy()).all()  # the lowered counts still step


_TRI = (np.eye(3), np.array([[0, 1, 2]]))


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: Ground(stiffness=0.0), "Ground.stiffness must be > 0"),
        (lambda: Ground(friction=-0.1), "Ground.friction must be >= 0"),
        (lambda: Ground(offset=0.06), r"Ground.offset must be in \[0, 0.05\]"),
        (lambda: Ground(up=(0.0, 2.0, 0.0)), "Ground.up must be a unit vector"),
        (lambda: Ground(height=float("nan")), "Ground.height must be a finite number"),
        (lambda: Sphere((0.0, 0.0, 0.0), 0.0), "Sphere.radius must be > 0"),
        (lambda: Sphere((0.0, float("inf"), 0.0), 1.0), "Sphere.center must be three finite numbers"),
        (lambda: Box((0.0, 0.0, 0.0), (1.0, -1.0, 1.0)), "Box.half_extents must be three finite numbers > 0"),
        (lambda: Box((0.0, 0.0), (1.0, 1.0, 1.0)), "Box.center must be three finite numbers"),
        (lambda: MeshCollider(_TRI[0], np.array([[0, 1, 3]])), "MeshCollider.faces index vertices 0..2"),
        (lambda: MeshCollider(_TRI[0], np.array([[0.0, 1.0, 2.0]])), "MeshCollider.faces must be"),
        (lambda: MeshCollider(np.zeros((3, 2)), _TRI[1]), "MeshCollider.vertices must be"),
        (lambda: MeshCollider(*_TRI, rotation=2.0 * np.eye(3)), "MeshCollider.rotation must be a 3 x 3 rotation"),
        (lambda: MeshCollider(*_TRI, stiffness=-1.0), "MeshCollider.stiffness must be > 0"),
    ],
)
def test_colliders_refuse_values_out_of_range(make, message):
    """A collider built through the API with a bad value is refused where it is made, naming the field, as a
    scene file's is, before any solver is built on it."""
    with pytest.raises(ValueError, match=message):
        make()

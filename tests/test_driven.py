"""Driven scenes: handles that hold a region to an animation, mesh obstacles, moving colliders.

References are independent of the simulator: SciPy's slerp of the keys, the same body pinned or on the
ground plane, the analytic acceleration of a block sliding down an incline.
"""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

import warpfem
from warpfem.build import keyed_motion
from warpfem.prep.shapes import box_tet_mesh
from warpfem.sim.drive import Handle, Motion
from warpfem.sim.integrate import Box, MeshCollider
from warpfem.sim.solver import Ground, Solver

KEYS = [
    [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    [0.1, 0.05, 0.02, 0.0, 10.0, 30.0, 0.0],
    [0.25, -0.05, 0.0, 0.03, -20.0, -30.0, 15.0],
]


def _block(lo, hi, cells, pinned=None, young=1e6, name="block", device="cpu", builder=None):
    v, t = box_tet_mesh(lo, hi, cells)
    b = builder or warpfem.ModelBuilder()
    warpfem.add_body(b, name, v, t, young, 0.3, 1000.0, pinned=None if pinned is None else pinned(v))
    return b, v


def _reference(keys, pivot, rest, time):
    """Rest points moved by the keys at ``time``: SciPy's slerp of the rotations, linear translations."""
    k = np.asarray(keys, float)
    t = float(np.clip(time, k[0, 0], k[-1, 0]))
    rot = Rotation.from_euler("xyz", k[:, 4:], degrees=True) if len(k) > 1 else None
    r = Slerp(k[:, 0], rot)([t])[0] if rot is not None else Rotation.from_euler("xyz", k[0, 4:], degrees=True)
    move = np.array([np.interp(t, k[:, 0], k[:, j]) for j in (1, 2, 3)])
    return r.apply(rest - pivot) + pivot + move


def test_held_vertices_follow_the_keys_at_every_frame(device):
    top = 0.5
    builder, v = _block((0, 0.3, 0), (0.2, top, 0.1), (4, 4, 2), pinned=lambda v: v[:, 1] > top - 1e-9, device=device)
    model = builder.finalize(device)
    held = np.flatnonzero(v[:, 1] > top - 1e-9)
    pivot = np.array([0.1, top, 0.05])
    solver = Solver(model, handles=[Handle(held, keyed_motion(KEYS, pivot))])
    sim = warpfem.Simulation.from_model(model, solver, substeps=3, fps=60.0)
    size = model.bodies[0].size
    for frame in range(1, 25):  # past the last key: the handle holds
        sim.step_frame()
        expected = _reference(KEYS, pivot, v[held], frame / 60.0)
        assert np.abs(sim.tet_points("block")[held] - expected).max() < 1e-5 * size, frame
        r, t = solver.handles[0].motion.at(frame / 60.0)  # what obstacles_at/handles_at report
        np.testing.assert_allclose(v[held] @ r.T + t, expected, atol=1e-9)
    assert np.isfinite(sim.tet_points("block")).all()


@pytest.mark.parametrize(
    ("substeps", "speed", "gap", "first"),
    [(3, 5.0, 0.05, None), (4, 2.3, 0.075, None), (4, 2.7, 0.075, None), (4, 2.3, 0.02, 5), (4, 2.9, 0.02, 6)],
)
def test_held_vertices_keep_the_keys_time_through_refined_frames(device, substeps, speed, gap, first):
    """A block thrown at the held one runs its impact's frames at more substeps: at 3 substeps and 5 m/s twice as
    many (1.25 and 1.5 times 3 are no whole numbers), at 4 and 2.3 m/s (1.06 times the approach limit a step)
    some at 1.25 times as many, steps four fifths as long, at 2.7 m/s some of them at 1.5 times, two thirds as
    long; thrown from 0.02 m, within a frame's travel, its first frame is one of those (``first`` steps: 5 at
    2.3 m/s, 6 at 2.9 m/s, 1.34 times the limit). The
    handle's clock counts them at their length, so the held vertices stay on the keys at every frame."""
    top = 0.5
    builder, v = _block((0, 0.3, 0), (0.2, top, 0.1), (4, 4, 2), pinned=lambda v: v[:, 1] > top - 1e-9, device=device)
    _block((0.2 + gap, 0.3, 0), (0.4 + gap, top, 0.1), (4, 4, 2), name="thrown", builder=builder)
    model = builder.finalize(device)
    held = np.flatnonzero(v[:, 1] > top - 1e-9)
    pivot = np.array([0.1, top, 0.05])
    solver = Solver(model, handles=[Handle(held, keyed_motion(KEYS, pivot))])
    sim = warpfem.Simulation.from_model(model, solver, substeps=substeps, fps=60.0)
    velocity = sim.states[0].v.numpy()
    velocity[len(v) :] = [-speed, 0.0, 0.0]
    sim.states[0].v.assign(velocity)
    size = model.bodies[0].size
    for frame in range(1, 13):
        sim.step_frame()
        if frame == 1 and first is not None:
            assert sim.totals.steps == first
        expected = _reference(KEYS, pivot, v[held], frame / 60.0)
        assert np.abs(sim.tet_points("block")[held] - expected).max() < 1e-5 * size, frame
    assert sim.totals.refined_frames >= 1
    refined, steps = sim.totals.refined_frames, sim.totals.steps
    if substeps == 3:
        assert steps == 12 * substeps + substeps * refined
    else:  # at least one refined frame ran fewer steps than twice as many
        assert 12 * substeps + refined * substeps // 4 <= steps < 12 * substeps + substeps * refined


def test_the_clock_counts_steps_of_either_refined_frame_whichever_comes_first(device):
    """The handle's clock ticks thirtieths of the scene's step, set before the first step: frames at 1.5, 2 and
    1.25 times the substeps (steps two thirds, half and four fifths as long) advance it by 20, 15 and 24 ticks,
    as many as the time they take, though a shorter step came before a longer one."""
    builder, v = _block((0, 0.3, 0), (0.2, 0.5, 0.1), (2, 2, 2), pinned=lambda v: v[:, 1] > 0.5 - 1e-9, device=device)
    model = builder.finalize(device)
    held = np.flatnonzero(v[:, 1] > 0.5 - 1e-9)
    solver = Solver(model, handles=[Handle(held, keyed_motion(KEYS, (0.1, 0.5, 0.05)))])
    sim = warpfem.Simulation.from_model(model, solver, substeps=4, fps=60.0)
    solver.drive.tick(sim.dt * 4 / 6)
    solver.drive.tick(sim.dt / 2)
    solver.drive.tick(sim.dt * 4 / 5)
    assert int(solver.drive.clock.numpy()[0]) == 59
    assert solver.drive.tick_dt * 59 == pytest.approx(sim.dt * (4 / 6 + 1 / 2 + 4 / 5), rel=1e-12)


def test_hanging_from_a_still_handle_sags_as_pinned(device):
    top = 0.6
    finals = []
    for handled in (False, True):
        builder, v = _block((0, 0.1, 0), (0.1, top, 0.1), (2, 10, 2), pinned=lambda v: v[:, 1] > top - 1e-9,
                            young=2e5)  # fmt: skip
        model = builder.finalize(device)
        held = np.flatnonzero(v[:, 1] > top - 1e-9)
        handles = [Handle(held, keyed_motion([[0, 0, 0, 0, 0, 0, 0]], (0, 0, 0)))] if handled else []
        solver = Solver(model, ground=None, handles=handles)
        sim = warpfem.Simulation.from_model(model, solver, substeps=2, fps=60.0)
        for _ in range(40):
            sim.step_frame()
        finals.append(sim.tet_points("block"))
    sag = finals[0][:, 1].min() - 0.1
    assert sag < -1e-3  # it does sag
    np.testing.assert_allclose(finals[1], finals[0], atol=1e-6)


def _floor_mesh(height, half=2.0, closed=False):
    if closed:  # a slab whose top face is at the height
        v, t = box_tet_mesh((-half, height - 0.5, -half), (half, height, half), (1, 1, 1))
        from warpfem.prep.tetmesh import boundary_faces

        faces = boundary_faces(t)
        used = np.unique(faces)
        remap = np.full(len(v), -1)
        remap[used] = np.arange(len(used))
        return v[used], remap[faces]
    v = np.array([[-half, height, -half], [half, height, -half], [half, height, half], [-half, height, half]])
    return v, np.array([[0, 2, 1], [0, 3, 2]])


@pytest.mark.parametrize("closed", [False, True], ids=["open", "closed"])
def test_resting_on_a_mesh_floor_as_on_the_ground(device, closed):
    height = 0.25
    rests = []
    for floor in ("ground", "mesh"):
        builder, v = _block((-0.1, height + 0.02, -0.1), (0.1, height + 0.22, 0.1), (3, 3, 3), young=1e5)
        model = builder.finalize(device)
        if floor == "ground":
            solver = Solver(model, ground=Ground(height=height))
        else:
            solver = Solver(model, ground=None, obstacles=[MeshCollider(*_floor_mesh(height, closed=closed))])
        sim = warpfem.Simulation.from_model(model, solver, substeps=4, fps=60.0)
        for _ in range(60):
            sim.step_frame()
        rests.append(sim.tet_points("block"))
    size = model.bodies[0].size
    assert abs(rests[0][:, 1].min() - height) < 0.01 * size  # it rests on the floor
    assert np.abs(rests[1] - rests[0]).max() < 1e-3 * size


def test_sliding_down_a_mesh_ramp_at_the_friction_the_angle_predicts(device):
    theta, mu, g = np.radians(25.0), 0.2, 9.81
    rot = Rotation.from_euler("z", -theta).as_matrix()  # down the slope towards +x
    half = 3.0
    ramp = np.array([[-half, 0, -0.5], [half, 0, -0.5], [half, 0, 0.5], [-half, 0, 0.5]]) @ rot.T
    down = rot @ np.array([1.0, 0.0, 0.0])
    normal = rot @ np.array([0.0, 1.0, 0.0])
    v, t = box_tet_mesh((-0.05, 0.0, -0.05), (0.05, 0.05, 0.05), (2, 1, 2))
    v = (v - [0, -0.001, 0]) @ rot.T - 1.5 * down  # sitting on the slope, 1 mm above it
    builder = warpfem.ModelBuilder()
    warpfem.add_body(builder, "block", v, t, 1e7, 0.3, 1000.0)
    model = builder.finalize(device)
    solver = Solver(model, ground=None, obstacles=[MeshCollider(ramp, np.array([[0, 2, 1], [0, 3, 2]]), friction=mu)])
    sim = warpfem.Simulation.from_model(model, solver, substeps=4, fps=60.0)
    times, along = [], []
    for frame in range(1, 46):
        sim.step_frame()
        if frame >= 10:  # landed and sliding
            times.append(frame / 60.0)
            along.append(sim.tet_points("block").mean(axis=0) @ down)
    accel = 2.0 * np.polyfit(times, along, 2)[0]
    expected = g * (np.sin(theta) - mu * np.cos(theta))
    assert accel == pytest.approx(expected, rel=0.03)
    assert abs((sim.tet_points("block") @ normal).min()) < 1e-3  # on the ramp (within 1 mm), not through it


def test_a_keyed_box_lifts_a_body_resting_on_it(device):
    """A platform rising at 0.5 m/s carries the body up with it (the contact holds the relative velocity)."""
    builder, v = _block((-0.1, 0.101, -0.1), (0.1, 0.3, 0.1), (3, 3, 3), young=1e5)
    model = builder.finalize(device)
    keys = [[0.3, 0, 0, 0, 0, 0, 0], [1.0, 0, 0.35, 0, 0, 0, 0]]
    platform = Box((0, 0, 0), (0.5, 0.1, 0.5), motion=keyed_motion(keys, (0, 0, 0)))
    solver = Solver(model, ground=None, obstacles=[platform])
    sim = warpfem.Simulation.from_model(model, solver, substeps=4, fps=60.0)
    for _ in range(66):  # 1.1 s: risen 0.35 m and stopped
        sim.step_frame()
    top = 0.1 + 0.35
    assert sim.tet_points("block")[:, 1].min() == pytest.approx(top, abs=2e-3)
    posed = sim.obstacles_at()[0]
    np.testing.assert_allclose(posed.matrix[:3, 3], (0, 0.35, 0), atol=1e-12)


def test_motion_holds_before_the_first_key_and_after_the_last():
    m = Motion([1.0, 2.0], [[0, 0, 0, 1], [0, 0, 1, 0]], [[0, 0, 0], [1, 0, 0]])
    r0, t0 = m.at(0.0)
    r3, t3 = m.at(3.0)
    np.testing.assert_allclose(r0, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(t3, (1, 0, 0), atol=1e-12)
    np.testing.assert_allclose(r3, Rotation.from_euler("z", 180, degrees=True).as_matrix(), atol=1e-12)
    with pytest.raises(ValueError):
        Motion([1.0, 1.0], [[0, 0, 0, 1]] * 2, [[0, 0, 0]] * 2)


def test_a_scene_without_handles_or_moving_obstacles_launches_nothing_for_them(device, monkeypatch):
    from test_collision import _count_launches

    builder, v = _block((0, 0.3, 0), (0.2, 0.5, 0.1), (2, 2, 2), pinned=lambda v: v[:, 1] > 0.5 - 1e-9)
    model = builder.finalize(device)
    still = Solver(model, obstacles=[Box((0, 0, 0), (1, 0.1, 1))])
    assert still.drive is None
    names = _count_launches(monkeypatch, still, model)
    assert "drive" not in names and "tick" not in names
    held = np.flatnonzero(v[:, 1] > 0.5 - 1e-9)
    # rotation updates off in both: the handle's first move turns tets (a second solve), a still body's does not
    driven = Solver(model, handles=[Handle(held, keyed_motion(KEYS, (0, 0, 0)))], rotation_updates=0)
    names = _count_launches(monkeypatch, driven, model)
    assert names.count("drive") == 1 and names.count("tick") == 1
    assert len(names) == len(_count_launches(monkeypatch, Solver(model, rotation_updates=0), model)) + 2


def test_the_shipped_driven_scenes_load():
    scenes = warpfem.default_scene_path().parent
    shake = warpfem.load_scene(scenes / "shake.toml")
    slide = warpfem.load_scene(scenes / "slide.toml")
    assert [h.name for h in shake.handles] == ["ears"] and [o.kind for o in slide.obstacles] == ["mesh", "mesh"]


@pytest.mark.slow
def test_bodies_slide_down_the_shipped_ramp_into_the_bowl(tmp_path):
    scene = warpfem.load_scene(warpfem.default_scene_path().parent / "slide.toml").with_frames(80)
    sim = warpfem.Simulation(scene, device="cpu", cache_dir=tmp_path)
    for _ in range(80):
        sim.step_frame()
    for points in sim.dense_points():
        centre = points.mean(axis=0)
        assert np.hypot(centre[0], centre[2]) < 1.0 and centre[1] < 0.6  # in the bowl, below its rim
    assert warpfem.frame_penetration(sim).below_relative < 0.01

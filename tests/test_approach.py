"""Which frames run more substeps, and how many: the approach watch against hand-worked cases."""

from pathlib import Path

import numpy as np
import pytest

import warpfem

LIMIT = 0.02
BALL = str(Path(__file__).resolve().parent / "data" / "golden" / "ball.obj")


def _two_balls(device: str, cache, gap: float, left_v: tuple, right_v: tuple) -> warpfem.Simulation:
    """Two balls side by side along x, their boxes ``gap`` m apart, at velocities ``left_v`` and ``right_v``
    (m/s), no gravity or ground, at 60 frames of 4 steps a second."""

    def ball(name: str, velocity: tuple) -> dict:
        return {"name": name, "mesh": BALL, "faces": 120, "scale": 0.15, "translate": [0, 1, 0], "velocity": velocity}

    doc = {
        "scene": {"frames": 1, "substeps": 4, "gravity": [0.0, 0.0, 0.0]},
        "ground": {"enabled": False},
        "collision": {"approach_limit": LIMIT},
        "object": [ball("left", left_v), ball("right", right_v)],
    }
    sim = warpfem.Simulation(warpfem.Scene.from_dict(doc, name="two_balls"), device=device, cache_dir=cache)
    x = sim.states[0].x.numpy()
    right = sim.body("right")
    span = slice(right.vertex_start, right.vertex_start + right.vertex_count)
    left_max = x[: right.vertex_start, 0].max()
    x[span, 0] += left_max - x[span, 0].min() + gap  # the right ball's box starts gap m past the left one's
    sim.states[0].x.assign(x)
    return sim


def _flags(sim: warpfem.Simulation) -> list[bool]:
    sim.approach.decide(sim.states[0], 1.0 / sim.fps, sim.dt)
    return [bool(f) for f in sim.approach.flags.numpy()]


def _flag(sim: warpfem.Simulation) -> bool:
    return _flags(sim)[0]


def _centre(sim: warpfem.Simulation, name: str) -> np.ndarray:
    """Body ``name``'s centre of mass (m)."""
    mass = sim.model.mass.numpy().astype(np.float64)
    b = sim.body(name)
    span = slice(b.vertex_start, b.vertex_start + b.vertex_count)
    x = sim.states[0].x.numpy()[span].astype(np.float64)
    return (x * mass[span, None]).sum(0) / mass[span].sum()


def _set_velocity(sim: warpfem.Simulation, name: str, velocity: np.ndarray) -> None:
    """Every tet vertex of body ``name`` at ``velocity`` (m/s)."""
    b = sim.body(name)
    v = sim.states[0].v.numpy()
    v[b.vertex_start : b.vertex_start + b.vertex_count] = velocity
    sim.states[0].v.assign(v)


@pytest.mark.parametrize(
    ("gap", "left_v", "right_v", "expected"),
    [
        (0.01, (5, 0, 0), (-5, 0, 0), True),  # near, closing at 10 m/s: 42 mm a step
        (0.01, (5, 0, 0), (5, 0, 0), False),  # near, moving together
        (0.01, (0.5, 0, 0), (-0.5, 0, 0), False),  # near, closing at 1 m/s: 4 mm a step
        (1.0, (5, 0, 0), (-5, 0, 0), False),  # closing at 10 m/s but 1 m apart: 0.17 m a frame
        (0.1, (5, 0, 0), (-5, 0, 0), True),  # 0.1 m apart: within the frame's 0.17 m
    ],
)
def test_a_frame_is_refined_where_two_near_bodies_close_fast(device, prep_cache, gap, left_v, right_v, expected):
    """The flag against the criterion worked by hand: near (the boxes' gap within what the two bodies' speeds
    cover in a frame) and fast (their closing speed times the step above ``LIMIT`` times the smaller size)."""
    sim = _two_balls(device, prep_cache, gap, left_v, right_v)
    size = min(b.size for b in sim.model.bodies)
    closing = np.linalg.norm(np.subtract(left_v, right_v)) * sim.dt
    reach = (np.linalg.norm(left_v) + np.linalg.norm(right_v)) / sim.fps
    assert (gap <= reach and closing > LIMIT * size) == expected  # the case is what it says
    assert _flag(sim) == expected


def test_a_refined_frame_takes_twice_the_steps_and_the_same_time(device, prep_cache):
    """A ball passing 0.1 m beside another at 10 m/s, across the gap between them: the frame runs 8 steps of
    1/480 s, and the ball moves as far as the frame's 1/60 s at its speed carries it (they do not touch)."""
    sim = _two_balls(device, prep_cache, 0.1, (0, 10, 0), (0, 0, 0))
    start = _centre(sim, "left")
    sim.step_frame()
    assert sim.totals.refined_frames == 1 and sim.totals.steps == 8
    assert np.allclose(_centre(sim, "left") - start, [0.0, 10.0 / 60.0, 0.0], atol=1e-4)


@pytest.mark.parametrize(
    ("ratio", "levels", "steps"),
    [(1.125, [True, False, False], 5), (1.375, [True, True, False], 6), (1.75, [True, True, True], 8)],
)
def test_a_frame_runs_the_fewest_substeps_that_keep_the_closing_within_the_limit(
    device, prep_cache, ratio, levels, steps
):
    """A ball passing 0.04 m beside another, closing on it at ``ratio`` times the limit a step (4 steps of 1/240 s):
    at 1.125 the frame's 5 steps of 1/300 s close by 0.9 times the limit, so it runs 5; at 1.375 those would close
    by 1.1 times and 6 steps of 1/360 s by 0.92 times, so it runs 6; at 1.75 6 steps would close by 1.17 times, so
    it runs 8 of 1/480 s (0.88 times). Either way the ball moves as far as the frame's 1/60 s at its speed
    carries it."""
    sim = _two_balls(device, prep_cache, 0.04, (0, 0, 0), (0, 0, 0))
    assert sim.approach.levels == (5, 6, 8)
    size = min(b.size for b in sim.model.bodies)
    speed = ratio * LIMIT * size / sim.dt
    _set_velocity(sim, "left", np.array([0.0, speed, 0.0]))
    assert _flags(sim) == levels
    start = _centre(sim, "left")
    sim.step_frame()
    assert sim.totals.refined_frames == 1 and sim.totals.steps == steps
    assert np.allclose(_centre(sim, "left") - start, [0.0, speed / 60.0, 0.0], atol=1e-4)


def test_an_odd_substep_count_refines_to_twice():
    """1.25 and 1.5 times an odd count are no whole numbers of steps: such a frame refines straight to twice; an
    even count not a multiple of 4 refines to 1.5 or 2 times, a multiple of 4 to 1.25 times too."""
    from warpfem.sim.approach import refined_substeps

    assert refined_substeps(3) == (6,) and refined_substeps(1) == (2,)
    assert refined_substeps(2) == (3, 4) and refined_substeps(6) == (9, 12)
    assert refined_substeps(4) == (5, 6, 8) and refined_substeps(8) == (10, 12, 16)


@pytest.mark.parametrize("limit", [-0.01, 1.0, float("nan")])
def test_a_bad_approach_limit_of_a_hand_built_model_is_refused(limit):
    """``Simulation.from_model`` refuses a limit outside [0, 1) or NaN, naming it, before it builds anything."""
    from warpfem.prep.shapes import box_tet_mesh

    builder = warpfem.ModelBuilder()
    for name, lo in (("a", 0.0), ("b", 0.3)):
        v, t = box_tet_mesh((lo, 0.0, 0.0), (lo + 0.2, 0.2, 0.2), (2, 2, 2))
        warpfem.add_body(builder, name, v, t, 1e6, 0.3, 1000.0)
    model = builder.finalize("cpu")
    with pytest.raises(ValueError, match=r"approach_limit must be >= 0 and < 1 .*got"):
        warpfem.Simulation.from_model(model, warpfem.Solver(model), approach_limit=limit)

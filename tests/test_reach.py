"""Bodies out of the still colliders' reach: the bounds hold against NumPy, and leaving those bodies out of the
static tests changes nothing a run computes."""

from __future__ import annotations

import numpy as np
import pytest

import warpfem


def _tower(device, asset, prep_cache) -> warpfem.Simulation:
    """Eight of the piles' armadillos (1 m, 500 faces) in two layers of 2 x 2, the upper 1.4 m above the lower,
    dropped onto the ground."""
    objects = [
        {
            "name": f"body_{i}",
            "mesh": str(asset("armadillo.off")),
            "faces": 500,
            "scale": 0.0066,
            "rotate": [0.0, 47.0 * i, 0.0],
            "translate": [1.1 * (i % 2 - 0.5), 0.7 + 1.4 * (i // 4), 1.1 * (i // 2 % 2 - 0.5)],
            "young": 1e6,
        }
        for i in range(8)
    ]
    scene = warpfem.Scene.from_dict({"scene": {"frames": 30}, "object": objects}, name="tower")
    return warpfem.Simulation(scene, device=device, cache_dir=prep_cache)


def _embedded(x: np.ndarray, cells: np.ndarray, cell: np.ndarray, bary: np.ndarray) -> np.ndarray:
    return np.einsum("pk,pkj->pj", bary, x[cells[cell]])


def test_leaving_bodies_out_of_reach_changes_nothing_a_run_computes(device, asset, prep_cache, monkeypatch):
    """Thirty frames of the tower with every body tested against the ground, then with the bodies out of its
    reach left out (as scenes of many bodies do): the same positions and velocities, bit for bit, and the
    upper layer was left out while it fell."""
    runs = []
    for reach in (False, True):
        monkeypatch.setattr("warpfem.sim.solver.REACH_BODIES", 0 if reach else 10**9)
        sim = _tower(device, asset, prep_cache)
        assert (sim.solver.reach is not None) == reach
        left_out = 0
        for _ in range(30):
            sim.step_frame()
            if reach:
                left_out += int((sim.solver.reach.clear.numpy() >= 0.0).sum())
        runs.append((sim.state().x.numpy(), sim.state().v.numpy()))
        if reach:
            assert left_out > 0
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    np.testing.assert_array_equal(runs[0][1], runs[1][1])


def test_the_bounds_of_bodies_left_out_hold_for_every_point(device, asset, prep_cache, monkeypatch):
    """Against NumPy, at each of the tower's first 20 frames: a body given a clearance has every skin point
    that much above the ground's offset (its clearance over its ``sum |w|``, as a step reports it) and farther
    than its fastest point moves in a step; a body marked free of the lift has every skin point and dense
    vertex above the lift's give below the ground."""
    from warpfem.kernels.integrate import LIFT_GIVE

    monkeypatch.setattr("warpfem.sim.solver.REACH_BODIES", 0)
    sim = _tower(device, asset, prep_cache)
    m, reach = sim.model, sim.solver.reach
    cells, cell_body = m.cells.numpy(), m.cell_body.numpy()
    skin_cell, skin_bary = m.skin_cell.numpy(), m.skin_bary.numpy()
    dense_cell, dense_bary = m.dense_cell.numpy(), m.dense_bary.numpy()
    size = m.body_size.numpy()
    offset = sim.solver.colliders.colliders[0].offset * size
    cleared = freed = 0
    for _ in range(20):
        sim.step_frame()
        x, v = sim.state().x.numpy(), sim.state().v.numpy()
        clear = reach.bound_step(sim.state().x, sim.state().v, sim.dt).numpy()
        free = reach.bound_lift(sim.state().x).numpy()
        skin, dense = _embedded(x, cells, skin_cell, skin_bary), _embedded(x, cells, dense_cell, dense_bary)
        skin_v = _embedded(v, cells, skin_cell, skin_bary)
        skin_body, dense_body = cell_body[skin_cell], cell_body[dense_cell]
        for b in np.flatnonzero(clear >= 0.0):
            mine = skin_body == b
            reported = (skin[mine, 1] - offset[b]) / np.abs(skin_bary[mine]).sum(axis=1)
            assert reported.min() >= clear[b] - 1e-6
            assert (skin[mine, 1] - offset[b]).min() > sim.dt * np.linalg.norm(skin_v[mine], axis=1).max()
            cleared += 1
        for b in np.flatnonzero(free):
            lowest = min(skin[skin_body == b, 1].min(), dense[dense_body == b, 1].min())
            assert lowest >= -LIFT_GIVE * size[b] - 1e-6
            freed += 1
    assert cleared > 0 and freed > 0


@pytest.mark.parametrize("kind", ["moving sphere", "mesh"])
def test_a_moving_collider_or_a_mesh_leaves_no_body_out(kind):
    """Their distances bound no box (a moving one's surface moves within the step; a mesh's reads as far
    outside past its reach): every body is tested, however far it is."""
    import warp as wp

    from warpfem.prep.shapes import box_tet_mesh
    from warpfem.sim.drive import Motion
    from warpfem.sim.integrate import MeshCollider, Sphere
    from warpfem.sim.model import ModelBuilder
    from warpfem.sim.reach import StaticReach
    from warpfem.sim.solver import Ground, Solver
    from warpfem.simulation import box_surface

    builder = ModelBuilder()
    for k in range(3):
        v, t = box_tet_mesh((2.0 * k, 5.0, 0.0), (2.0 * k + 0.3, 5.3, 0.3), (2, 2, 2))
        warpfem.add_body(builder, f"b{k}", v, t, 1e6, 0.3, 1000.0)
    model = builder.finalize("cpu")
    if kind == "mesh":
        obstacle = MeshCollider(*box_surface(np.array([-1.0, -1.0, -1.0]), np.array([1.0, 0.0, 1.0])))
    else:
        keys = Motion([0.0, 1.0], [[0, 0, 0, 1], [0, 0, 0, 1]], [[0, 0, 0], [0, 1, 0]])
        obstacle = Sphere(center=(0.0, -5.0, 0.0), radius=1.0, motion=keys)
    solver = Solver(model, ground=None, obstacles=[obstacle])
    reach = StaticReach(model, solver.colliders)
    v = wp.zeros_like(model.rest_x)
    assert (reach.bound_step(model.rest_x, v, 1 / 240).numpy() < 0.0).all()
    assert not reach.bound_lift(model.rest_x).numpy().any()
    far = StaticReach(model, Solver(model, ground=Ground()).colliders)  # the ground alone: all out
    assert (far.bound_step(model.rest_x, v, 1 / 240).numpy() >= 0.0).all()
    assert far.bound_lift(model.rest_x).numpy().all()

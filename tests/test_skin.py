"""The skin's static contacts read only the skin points a collider can reach: runs land where reading every one does."""

import numpy as np
import pytest
import warp as wp
from warpfem.kernels import skin as KS
from warpfem.kernels.integrate import Colliders

import warpfem

BOX = {"kind": "box", "center": [0.0, -0.5, 0.0], "half_extents": [2.0, 0.5, 2.0]}
RISING_BOX = {**BOX, "keys": [[0.0, 0, 0, 0, 0, 0, 0], [0.5, 0, 0.3, 0, 0, 20, 0]]}
BALL = {"kind": "sphere", "center": [0.0, -1.0, 0.0], "radius": 1.0}


@wp.kernel
def list_every_point(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    cells: wp.array(dtype=wp.vec4i),
    skin_cell: wp.array(dtype=wp.int32),
    skin_bary: wp.array(dtype=wp.vec4),
    cell_body: wp.array(dtype=wp.int32),
    body_momentum: wp.array(dtype=wp.vec3),
    body_mass: wp.array(dtype=float),
    colliders: Colliders,
    dt: float,
    listed_out: wp.array(dtype=wp.int32),
    list_out: wp.array(dtype=wp.int32),
    clear_out: wp.array(dtype=float),
):
    """``kernels.skin.skin_reach``'s place, listing every skin point (the contact kernel then reads them all)."""
    i = wp.tid()
    list_out[wp.atomic_add(listed_out, 0, 1)] = i


def _scene(speed: float, obstacle: dict | None, turned: float) -> dict:
    """A bunny (0.8 m, 2e5 Pa) tilted by ``turned`` degrees, thrown down at ``speed`` (m/s) onto the ground or,
    with the ground off, onto ``obstacle`` (the scene's ``[[obstacle]]`` table)."""
    bunny = {"name": "bunny", "mesh": "builtin:bunny", "subdivide": 0, "faces": 400, "scale": 0.5,
             "rotate": [turned, 30.0, 0.0], "translate": [0.0, 0.3, 0.0], "velocity": [0.0, -speed, 0.0],
             "young": 2e5}  # fmt: skip
    doc = {"scene": {"frames": 30, "substeps": 4}, "object": [bunny]}
    if obstacle is not None:
        doc["ground"] = {"enabled": False}
        doc["obstacle"] = [obstacle]
    return doc


def _landed(device: str, doc: dict) -> np.ndarray:
    sim = warpfem.Simulation(warpfem.Scene.from_dict(doc, name="throw"), device=device)
    for _ in range(doc["scene"]["frames"]):
        sim.step_frame()
    return sim.dense_points("bunny")


@pytest.mark.parametrize(
    ("speed", "obstacle", "turned"),
    [(30.0, None, 15.0), (3.0, None, 60.0), (10.0, RISING_BOX, 15.0), (10.0, BALL, 40.0), (2.0, BOX, 0.0)],
)
def test_a_step_reads_every_skin_point_a_collider_reaches(device, monkeypatch, speed, obstacle, turned):
    """A step's static contacts on the skin read only the points whose clearance from the planes, spheres and
    boxes their own or their body's speed can cover within the step: a bunny thrown at the ground at 3-30 m/s,
    onto a box rising and turning to meet it, onto a ball and resting on a box lands exactly where the same run
    reading every skin point lands (float32 summation order aside on CUDA)."""
    doc = _scene(speed, obstacle, turned)
    listed = _landed(device, doc)
    monkeypatch.setattr(KS, "skin_reach", list_every_point)
    every = _landed(device, doc)
    assert np.ptp(every[:, 1]) > 0.1  # a real landing, not a body that never came near
    atol = 0.0 if device == "cpu" else 1e-5
    np.testing.assert_allclose(listed, every, rtol=0.0, atol=atol)


def test_a_body_thrown_onto_a_still_mesh_never_sinks_into_it(device, tmp_path):
    """Thrown at 10 m/s onto a box given as a mesh (the ground off): the dense surface is never inside it by more
    than the skin points' tolerance (0.02 % of the size, measured against the box's own shape), as on a box
    collider, and deeper with the penalty alone (the mesh's lift is a launch of its own)."""
    import trimesh

    box = trimesh.creation.box(extents=[4.0, 1.0, 4.0])
    box.apply_translation([0.0, -0.5, 0.0])
    box.export(tmp_path / "box.obj")
    deepest = []
    for lift in (True, False):
        doc = _scene(10.0, {"kind": "mesh", "mesh": str(tmp_path / "box.obj")}, 15.0)
        doc["solver"] = {"static_lift": lift}
        sim = warpfem.Simulation(warpfem.Scene.from_dict(doc, name="throw"), device=device)
        size = float(np.linalg.norm(np.ptp(sim.dense_points("bunny"), axis=0)))
        depth = 0.0
        for _ in range(doc["scene"]["frames"]):
            sim.step_frame()
            q = np.abs(sim.dense_points("bunny") - [0.0, -0.5, 0.0]) - [2.0, 0.5, 2.0]
            depth = max(depth, float(-q.max(axis=1).min()))
        deepest.append(depth / size)
    assert deepest[0] < 0.0002, deepest
    assert deepest[1] > 2 * deepest[0] + 0.0002, deepest

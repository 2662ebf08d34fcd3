"""Obstacles and handles in the written USD: prims whose transform follows their keys at every frame."""

from __future__ import annotations

import os

import numpy as np
import pytest
import trimesh

import warpfem

SCENE = """
[scene]
frames = 6
substeps = 2

[ground]
height = -1.0

[[object]]
name = "ball"
mesh = "ball.obj"
faces = 120
scale = 0.2
translate = [0.0, 0.5, 0.0]

[[obstacle]]
name = "lift"
kind = "box"
center = [0.0, 0.0, 0.0]
half_extents = [0.5, 0.1, 0.5]
keys = [[0.0, 0, 0, 0, 0, 0, 0], [0.1, 0.0, 0.3, 0.0, 0, 0, 0]]

[[obstacle]]
kind = "sphere"
center = [2.0, 0.0, 0.0]
radius = 0.25

[[handle]]
name = "top"
object = "ball"
min = [-1.0, 0.6, -1.0]
max = [1.0, 1.0, 1.0]
keys = [[0.0, 0, 0, 0, 0, 0, 0], [0.05, 0.1, 0.0, 0.0, 0, 0, 0]]
"""


@pytest.mark.parametrize("save_every", [10.0, 0.0], ids=["one file", "clips"])
def test_obstacles_and_handles_follow_their_keys_in_the_file(tmp_path, save_every):
    """Each prop's world vertices (usd-core's transform of its points) at frame f are its rest vertices moved by
    the keys' translation at f / fps, worked out here by hand; the handle is a guide, the obstacles are not."""
    from pxr import Usd, UsdGeom

    trimesh.creation.icosphere(subdivisions=2).export(tmp_path / "ball.obj")
    (tmp_path / "scene.toml").write_text(SCENE)
    scene = warpfem.load_scene(tmp_path / "scene.toml")
    sim = warpfem.Simulation(scene, device="cpu", cache_dir=os.environ.get("WARPFEM_CACHE") or tmp_path)
    rest = {
        p.name: p.matrix[:3, :3] @ p.vertices.T + p.matrix[:3, 3:] for p in (*sim.obstacles_at(0), *sim.handles_at(0))
    }
    from warpfem.runner import record

    record(sim, tmp_path / "a.usdc", save_every=save_every)
    stage = Usd.Stage.Open(str(tmp_path / "a.usdc"))
    cache = UsdGeom.XformCache()
    moved = {
        "obstacles/lift": lambda t: np.array([0.0, 0.3 * min(t / 0.1, 1.0), 0.0]),
        "obstacles/obstacle1": lambda t: np.zeros(3),
        "handles/top": lambda t: np.array([0.1 * min(t / 0.05, 1.0), 0.0, 0.0]),
    }
    for path, shift in moved.items():
        prim = stage.GetPrimAtPath(f"/World/{path}")
        assert prim.IsA(UsdGeom.Mesh), path
        purpose = UsdGeom.Imageable(prim).ComputePurpose()
        assert purpose == (UsdGeom.Tokens.guide if path.startswith("handles") else UsdGeom.Tokens.default_)
        points = np.array(UsdGeom.Mesh(prim).GetPointsAttr().Get())
        for frame in range(scene.frames + 1):
            cache.SetTime(Usd.TimeCode(frame))
            m = np.array(cache.GetLocalToWorldTransform(prim))  # row vectors
            world = points @ m[:3, :3] + m[3, :3]
            expected = rest[path.split("/")[1]].T + shift(frame / scene.fps)
            np.testing.assert_allclose(world, expected, atol=1e-5, err_msg=f"{path} at frame {frame}")
    ball = UsdGeom.Mesh(stage.GetPrimAtPath("/World/ball")).GetPointsAttr()
    assert ball.GetTimeSamples() == [float(f) for f in range(scene.frames + 1)]


def test_a_body_named_like_the_obstacles_group_is_one_line(tmp_path):
    trimesh.creation.icosphere(subdivisions=2).export(tmp_path / "ball.obj")
    (tmp_path / "scene.toml").write_text(
        SCENE.replace('name = "ball"', 'name = "obstacles"').replace('object = "ball"', 'object = "obstacles"')
    )
    scene = warpfem.load_scene(tmp_path / "scene.toml")
    with pytest.raises(warpfem.InputError, match="a body is named 'obstacles'"):
        warpfem.run(scene, tmp_path / "a.usdc", device="cpu", cache=False)
    assert not (tmp_path / "a.usdc").exists()

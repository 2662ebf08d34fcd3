"""Dense meshes read from USD files: a transformed, quad-faced mesh, prim choice, and one-line errors."""

import numpy as np
import pytest
import trimesh

import warpfem
from warpfem.errors import InputError
from warpfem.prep.surface import read_usd_mesh

CUBE = """#usda 1.0
(
    metersPerUnit = {mpu}
    upAxis = "Y"
)

def Xform "World" (
)
{{
    double3 xformOp:translate = (1, 2, 3)
    float3 xformOp:scale = (2, 2, 2)
    uniform token[] xformOpOrder = ["xformOp:translate", "xformOp:scale"]

    def Mesh "Cube"
    {{
        uniform token orientation = "leftHanded"
        int[] faceVertexCounts = [4, 4, 4, 4, 4, 4]
        int[] faceVertexIndices = [0, 1, 3, 2, 4, 6, 7, 5, 0, 4, 5, 1, 2, 3, 7, 6, 0, 2, 6, 4, 1, 5, 7, 3]
        point3f[] points = [(-0.5, -0.5, -0.5), (0.5, -0.5, -0.5), (-0.5, 0.5, -0.5), (0.5, 0.5, -0.5),
                            (-0.5, -0.5, 0.5), (0.5, -0.5, 0.5), (-0.5, 0.5, 0.5), (0.5, 0.5, 0.5)]
    }}
{extra}
}}
"""

SECOND = """
    def Mesh "Other"
    {
        int[] faceVertexCounts = [3, 3, 3, 3]
        int[] faceVertexIndices = [0, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 3]
        point3f[] points = [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)]
    }
"""


def _write(tmp_path, mpu=1.0, extra=""):
    path = tmp_path / "cube.usda"
    path.write_text(CUBE.format(mpu=mpu, extra=extra))
    return path


def test_a_quad_mesh_comes_in_triangulated_and_placed_in_metres(tmp_path):
    points, faces = read_usd_mesh(_write(tmp_path, mpu=0.01))
    assert faces.shape == (12, 3)
    # world = 2 * local + (1, 2, 3), in centimetres: a 2 cm cube centred at (1, 2, 3) cm
    np.testing.assert_allclose(points.min(0), [0.0, 0.01, 0.02], atol=1e-9)
    np.testing.assert_allclose(points.max(0), [0.02, 0.03, 0.04], atol=1e-9)
    mesh = trimesh.Trimesh(points, faces)
    # its quads wind clockwise seen from outside, as a left-handed mesh does: turned to wind outward
    assert mesh.is_watertight and mesh.volume == pytest.approx(0.02**3, rel=1e-9)


def test_several_meshes_need_a_prim(tmp_path):
    path = _write(tmp_path, extra=SECOND)
    with pytest.raises(InputError, match="2 meshes .*/World/Cube, /World/Other.*prim"):
        read_usd_mesh(path)
    assert read_usd_mesh(path, "/World/Other")[1].shape == (4, 3)
    with pytest.raises(InputError, match="/World/Nope is not a UsdGeom.Mesh"):
        read_usd_mesh(path, "/World/Nope")


def test_a_scene_object_from_usd_runs(tmp_path):
    path = _write(tmp_path, mpu=1.0, extra=SECOND)
    doc = {
        "scene": {"frames": 2},
        "object": [{"name": "cube", "mesh": "cube.usda", "prim": "/World/Cube", "faces": 100, "scale": 0.2}],
    }
    sim = warpfem.Simulation(warpfem.Scene.from_dict(doc, base_dir=tmp_path), device="cpu", cache=False)
    rest = sim.dense_points("cube")
    np.testing.assert_allclose(rest.max(0) - rest.min(0), [0.4, 0.4, 0.4], atol=1e-6)  # 2 m * 0.2
    sim.step_frame()
    bad = {**doc, "object": [{**doc["object"][0], "mesh": str(path), "prim": "World"}]}
    with pytest.raises(InputError, match="prim"):
        warpfem.Scene.from_dict(bad, base_dir=tmp_path)
    trimesh.creation.box().export(tmp_path / "box.obj")
    with pytest.raises(InputError, match="prim"):
        warpfem.Scene.from_dict({**doc, "object": [{**doc["object"][0], "mesh": "box.obj"}]}, base_dir=tmp_path)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('#usda 1.0\ndef Mesh "M" {\n  point3f[] points = [(0, 0\n', "unreadable USD file"),
        ('#usda 1.0\ndef Xform "World" {}\n', "no UsdGeom.Mesh"),
        (
            '#usda 1.0\ndef Mesh "M" {\n  int[] faceVertexCounts = [2]\n  int[] faceVertexIndices = [0, 1]\n'
            "  point3f[] points = [(0, 0, 0), (1, 0, 0)]\n}\n",
            "no faces, or faces of fewer than 3",
        ),
        (
            '#usda 1.0\ndef Mesh "M" {\n  int[] faceVertexCounts = [3, 3, 3, 3]\n'
            "  int[] faceVertexIndices = [0, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 3]\n"
            "  point3f[] points = [(0, 0, 0), (1, 0, 0), (0, nan, 0), (0, 0, 1)]\n}\n",
            "NaN or Inf",
        ),
    ],
)
def test_broken_usd_meshes_are_one_line_errors(tmp_path, capsys, text, message):
    from warpfem.cli import main

    (tmp_path / "bad.usda").write_text(text)
    assert main(["prepare", str(tmp_path / "bad.usda"), "--no-cache"]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("warpfem:")]
    assert len(err) == 1 and "bad.usda" in err[0] and message in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.usda"]

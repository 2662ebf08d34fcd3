"""Bad handles and obstacles in a scene: one line naming the file and key, exit code 2, nothing written."""

import numpy as np
import pytest
import trimesh
from pxr import Gf, Usd, UsdGeom

import warpfem
from warpfem.cli import main

BALL = """
[scene]
frames = 2
substeps = 1
[[object]]
name = "ball"
mesh = "ball.obj"
faces = 120
scale = 0.5
translate = [0.0, 0.6, 0.0]
"""

HANDLE = '[[handle]]\nobject = "ball"\nmin = [-1, 0.9, -1]\nmax = [1, 2, 1]\n'
KEYS = "keys = [[0, 0, 0, 0, 0, 0, 0], [1, 0.1, 0, 0, 0, 0, 0]]\n"


def _usd(path, scale_at_1=1.0):
    """A stage with /World/Hand moving along x over time codes 0..24 at 24 per second (scaling at 24 if asked)."""
    stage = Usd.Stage.CreateNew(str(path))
    stage.SetTimeCodesPerSecond(24)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    hand = UsdGeom.Xform.Define(stage, "/World/Hand")
    move = hand.AddTranslateOp()
    move.Set(Gf.Vec3d(0, 0, 0), 0)
    move.Set(Gf.Vec3d(0.3, 0, 0), 24)
    spin = hand.AddRotateYOp()
    spin.Set(0.0, 0)
    spin.Set(90.0, 24)
    if scale_at_1 != 1.0:
        scale = hand.AddScaleOp()
        scale.Set(Gf.Vec3f(1, 1, 1), 0)
        scale.Set(Gf.Vec3f(scale_at_1, 1, 1), 24)
    stage.GetRootLayer().Save()


SKELETON = """#usda 1.0
(
    timeCodesPerSecond = 10
    metersPerUnit = 1
)

def SkelRoot "Rig"
{
    def Skeleton "Skel" (
        prepend apiSchemas = ["SkelBindingAPI"]
    )
    {
        uniform token[] joints = ["root", "root/arm"]
        uniform matrix4d[] bindTransforms = [
            ((1,0,0,0),(0,1,0,0),(0,0,1,0),(0,0,0,1)),
            ((1,0,0,0),(0,1,0,0),(0,0,1,0),(0,1,0,1)),
        ]
        uniform matrix4d[] restTransforms = [
            ((1,0,0,0),(0,1,0,0),(0,0,1,0),(0,0,0,1)),
            ((1,0,0,0),(0,1,0,0),(0,0,1,0),(0,1,0,1)),
        ]
        rel skel:animationSource = </Rig/Skel/Anim>

        def SkelAnimation "Anim"
        {
            uniform token[] joints = ["root", "root/arm"]
            float3[] translations.timeSamples = {0: [(0, 0, 0), (0, 1, 0)], 10: [(1, 0, 0), (0, 1, 0)]}
            quatf[] rotations.timeSamples = {
                0: [(1, 0, 0, 0), (1, 0, 0, 0)],
                10: [(1, 0, 0, 0), (0.70710678, 0, 0, 0.70710678)],
            }
            half3[] scales = [(1, 1, 1), (1, 1, 1)]
        }
    }
}
"""
"""A root joint moving 1 m along x over a second and an arm 1 m above it turning 90 degrees about z meanwhile."""


@pytest.fixture
def folder(tmp_path):
    trimesh.creation.icosphere(subdivisions=3).export(tmp_path / "ball.obj")
    (tmp_path / "garbage.obj").write_text("v 0 0 nonsense\nf 1 2\n")
    (tmp_path / "plane.obj").write_text("v -1 0 -1\nv 1 0 -1\nv 1 0 1\nv -1 0 1\nf 1 3 2\nf 1 4 3\n")
    _usd(tmp_path / "hand.usda")
    _usd(tmp_path / "stretch.usda", scale_at_1=2.0)
    (tmp_path / "skel.usda").write_text(SKELETON)
    return tmp_path


CASES = [
    ("handle of no object", HANDLE.replace('"ball"', '"cube"') + KEYS, "handle[0]: object", "ball"),
    ("keys not increasing", HANDLE + "keys = [[0, 0, 0, 0, 0, 0, 0], [0, 1, 0, 0, 0, 0, 0]]\n", "handle[0]: keys[1]",
     "strictly increasing"),
    ("short key", HANDLE + "keys = [[0, 0, 0, 0]]\n", "handle[0]: keys[0]", "7 numbers"),
    ("negative time", HANDLE + "keys = [[-1, 0, 0, 0, 0, 0, 0]]\n", "handle[0]: keys[0]", ">= 0"),
    ("keys and usd", HANDLE + KEYS + 'usd = "hand.usda"\nprim = "/World/Hand"\n', "handle[0]: keys", "only one"),
    ("neither keys nor usd", HANDLE, "handle[0]: keys", "required"),
    ("usd missing", HANDLE + 'usd = "none.usda"\nprim = "/World/Hand"\n', "handle[0]: usd", "not found"),
    ("usd without prim", HANDLE + 'usd = "hand.usda"\n', "handle[0]: prim", "animated prim"),
    ("usd prim missing", HANDLE + 'usd = "hand.usda"\nprim = "/World/Foot"\n', "handle[0]: usd", "no prim"),
    ("usd prim scales", HANDLE + 'usd = "stretch.usda"\nprim = "/World/Hand"\n', "handle[0]: usd", "rigid"),
    ("prim and joint", HANDLE + 'usd = "skel.usda"\nprim = "/Rig"\njoint = "/Rig/Skel:root"\n', "handle[0]: prim",
     "only one"),
    ("joint without its skeleton", HANDLE + 'usd = "skel.usda"\njoint = "root/arm"\n', "handle[0]: joint",
     "/Path/To/Skeleton:joint/path"),
    ("joint of no skeleton", HANDLE + 'usd = "skel.usda"\njoint = "/Rig:root"\n', "handle[0]: usd", "Skeleton prim"),
    ("no such joint", HANDLE + 'usd = "skel.usda"\njoint = "/Rig/Skel:root/leg"\n', "handle[0]: usd",
     "joints: root, root/arm"),
    ("box holds nothing", HANDLE.replace("0.9", "1.5") + KEYS, "handle[0]: min, max", "holds no tet vertex"),
    ("handle over a pin", HANDLE + KEYS, "handle[0]: min, max", "pin box"),
    ("unknown handle key", HANDLE + KEYS + "speed = 2\n", "handle[0]: speed", "not a known key"),
    ("min above max", HANDLE.replace("[1, 2, 1]", "[1, 0.5, 1]") + KEYS, "handle[0]: min", "<= max"),
    ("mesh obstacle without mesh", '[[obstacle]]\nkind = "mesh"\n', "obstacle[0]: mesh", "required"),
    ("mesh obstacle unreadable", '[[obstacle]]\nkind = "mesh"\nmesh = "garbage.obj"\n', "obstacle[0]: mesh",
     "garbage.obj"),
    ("mesh obstacle with center", '[[obstacle]]\nkind = "mesh"\nmesh = "plane.obj"\ncenter = [0, 0, 0]\n',
     "obstacle[0]: center", "spheres and boxes"),
    ("sphere with scale", '[[obstacle]]\nkind = "sphere"\ncenter = [0, 0, 0]\nradius = 1\nscale = 2\n',
     "obstacle[0]: scale", "mesh"),
    ("bad obstacle keys", '[[obstacle]]\nkind = "box"\ncenter = [0, 0, 0]\nhalf_extents = [1, 1, 1]\nkeys = [1, 2]\n',
     "obstacle[0]: keys[0]", "7 numbers"),
    ("mesh scale zero", '[[obstacle]]\nkind = "mesh"\nmesh = "plane.obj"\nscale = 0\n', "obstacle[0]: scale", "> 0"),
]  # fmt: skip


@pytest.mark.parametrize(("text", "key", "phrase"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_driven_input_is_one_line_exit_2_nothing_written(folder, capsys, text, key, phrase):
    scene = folder / "scene.toml"
    body = BALL
    if "pin box" in phrase:
        body = BALL.replace("translate", "pin_min = [-1, 1.0, -1]\npin_max = [1, 2, 1]\ntranslate")
    scene.write_text(body + text)
    out = folder / "out.usdc"
    code = main(["run", str(scene), "--out", str(out), "--device", "cpu", "--cache-dir", str(folder / "cache")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1, err
    assert str(scene) in err[0] and key in err[0] and phrase in err[0], err[0]
    assert not out.exists() and not list(folder.glob("out*"))


def test_a_handle_follows_a_usd_prim(folder):
    """Held vertices follow the prim's transform relative to time 0: its translation and its turn about y."""
    scene = folder / "scene.toml"
    scene.write_text(BALL.replace("frames = 2", "frames = 30") + HANDLE + 'usd = "hand.usda"\nprim = "/World/Hand"\n')
    sim = warpfem.Simulation(warpfem.load_scene(scene), device="cpu", cache_dir=folder / "cache")
    rest = sim.tet_points("ball")
    held = np.flatnonzero(np.all((rest >= (-1, 0.9, -1)) & (rest <= (1, 2, 1)), axis=1))
    for frame in range(1, 31):
        sim.step_frame()
        t = min(frame / 60.0, 1.0)  # time codes 0..24 at 24 per second: one second
        angle = np.radians(90.0 * t)
        r = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
        expected = rest[held] @ r.T + (0.3 * t, 0, 0)  # USD: scale, rotate, then translate (ops in order)
        assert np.abs(sim.tet_points("ball")[held] - expected).max() < 1e-3 * sim.model.bodies[0].size


def test_a_handle_follows_a_usd_skel_joint(folder):
    """Held vertices follow the arm joint's world transform relative to time 0, worked out by hand: the joint
    moves from (0, 1, 0) to (t, 1, 0) and turns by 90 t degrees about z over t = 0..1 s."""
    scene = folder / "scene.toml"
    text = BALL.replace("frames = 2", "frames = 30") + HANDLE + 'usd = "skel.usda"\njoint = "/Rig/Skel:root/arm"\n'
    scene.write_text(text)
    sim = warpfem.Simulation(warpfem.load_scene(scene), device="cpu", cache_dir=folder / "cache")
    rest = sim.tet_points("ball")
    held = np.flatnonzero(np.all((rest >= (-1, 0.9, -1)) & (rest <= (1, 2, 1)), axis=1))
    for frame in range(1, 31):
        sim.step_frame()
        t = frame / 60.0
        angle = np.radians(90.0 * t)
        r = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
        expected = (rest[held] - (0, 1, 0)) @ r.T + (t, 1, 0)
        assert np.abs(sim.tet_points("ball")[held] - expected).max() < 1e-3 * sim.model.bodies[0].size

"""Scene files: defaults, every documented error as one line naming file and key, paths."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from warpfem.errors import InputError
from warpfem.scene import (
    CameraConfig,
    CollisionConfig,
    GroundConfig,
    ObjectConfig,
    Scene,
    SolverConfig,
    default_scene_path,
    load_scene,
)

MINIMAL = """
[[object]]
name = "bunny"
mesh = "builtin:bunny"
"""


def write(tmp_path: Path, text: str, name: str = "scene.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_scene_solver_defaults_are_the_solvers():
    from warpfem.sim.solver import DEFAULT_CONTACT_PASSES, DEFAULT_ROTATION_TOLERANCE, DEFAULT_ROTATION_UPDATES

    assert SolverConfig().contact_passes == DEFAULT_CONTACT_PASSES
    assert SolverConfig().rotation_updates == DEFAULT_ROTATION_UPDATES
    assert SolverConfig().rotation_tolerance == DEFAULT_ROTATION_TOLERANCE


def test_fixed_mode_without_a_count_runs_a_hundred_iterations(tmp_path):
    """The default cg_iterations (400) is a cap for tolerance mode; fixed mode runs that many every solve, so a
    fixed-mode scene that names no count gets 100, and one that names a count keeps it."""
    scene = load_scene(write(tmp_path, '[solver]\ncg_mode = "fixed"\n' + MINIMAL))
    assert (scene.solver.cg_mode, scene.solver.cg_iterations, scene.solver.stop_tolerance) == ("fixed", 100, 0.0)
    scene = load_scene(write(tmp_path, '[solver]\ncg_mode = "fixed"\ncg_iterations = 30\n' + MINIMAL))
    assert scene.solver.cg_iterations == 30


def test_every_default_applied(tmp_path):
    scene = load_scene(write(tmp_path, MINIMAL))
    assert (scene.frames, scene.fps, scene.substeps) == (120, 60.0, 4)
    assert scene.gravity == (0.0, -9.81, 0.0)
    assert scene.up_axis == "Y"
    assert scene.solver == SolverConfig(cg_mode="tolerance", cg_iterations=400, cg_tolerance=1e-4)
    assert scene.ground == GroundConfig(enabled=True, height=0.0, stiffness=1e7, friction=0.5, offset=0.0008)
    assert scene.collision == CollisionConfig(enabled=True, stiffness=1e7, friction=0.5)
    assert scene.camera == CameraConfig(position=None, target=None, fov=35.0)
    assert scene.obstacles == []
    (obj,) = scene.objects
    assert obj == ObjectConfig(
        name="bunny",
        mesh="builtin:bunny",
        subdivide=0,
        scale=1.0,
        rotate=(0.0, 0.0, 0.0),
        translate=(0.0, 0.0, 0.0),
        velocity=(0.0, 0.0, 0.0),
        faces=1000,
        maxh=0.2,
        young=1e5,
        poisson=0.3,
        density=1000.0,
        damping_mass=0.0,
        damping_stiffness=0.0,
        pin_min=None,
        pin_max=None,
    )
    assert obj.is_builtin
    assert scene.dt == pytest.approx(1.0 / 240.0)


def test_values_read_and_ints_become_floats(tmp_path):
    text = """
[scene]
frames = 10
fps = 30
substeps = 5
gravity = [0, 0, -9.81]
up_axis = "Z"

[solver]
cg_mode = "fixed"
cg_iterations = 20
cg_tolerance = 0.001

[ground]
enabled = false
height = -1
stiffness = 2e5
friction = 0

[[object]]
name = "a_1"
mesh = "builtin:bunny"
subdivide = 4
scale = 2
rotate = [90, 0, 45]
translate = [1, 2, 3]
velocity = [0, -1, 0]
faces = 20000
maxh = 1
young = 1e6
poisson = 0
density = 500
damping_mass = 0.1
damping_stiffness = 0.01
pin_min = [-1, -1, -1]
pin_max = [1, 1, 1]
"""
    scene = load_scene(write(tmp_path, text))
    assert scene.frames == 10 and isinstance(scene.fps, float) and scene.fps == 30.0
    assert scene.dt == pytest.approx(1.0 / 150.0)
    assert scene.gravity == (0.0, 0.0, -9.81) and scene.up_axis == "Z"
    assert scene.solver == SolverConfig("fixed", 20, 0.001)
    assert scene.ground == GroundConfig(False, -1.0, 2e5, 0.0)
    obj = scene.objects[0]
    assert obj.scale == 2.0 and isinstance(obj.scale, float)
    assert obj.rotate == (90.0, 0.0, 45.0) and all(isinstance(v, float) for v in obj.rotate)
    assert (obj.subdivide, obj.faces, obj.maxh, obj.poisson) == (4, 20000, 1.0, 0.0)
    assert obj.pin_min == (-1.0, -1.0, -1.0) and obj.pin_max == (1.0, 1.0, 1.0)


# (description, scene text, the key the message must name, a phrase it must hold)
OBJ = '[[object]]\nname = "bunny"\nmesh = "builtin:bunny"\n'
ERRORS = [
    ("unknown top-level key", "colour = 1\n" + OBJ, "colour", "not a known table"),
    ("unknown table", "[render]\nsamples = 4\n" + OBJ, "render", "not a known table"),
    ("unknown key in scene", "[scene]\nframez = 3\n" + OBJ, "scene.framez", "did you mean frames"),
    ("unknown key in solver", "[solver]\ncg = 3\n" + OBJ, "solver.cg", "not a known key"),
    ("unknown key in object", OBJ + "yung = 5.0\n", "object[0] 'bunny': yung", "did you mean young"),
    ("sub-table in object", OBJ + "[object.extra]\na = 1\n", "object[0] 'bunny': extra", "not a known key"),
    ("string for number", OBJ + 'young = "1e5"\n', "object[0] 'bunny': young", "must be a number"),
    ("bool for number", "[scene]\nfps = true\n" + OBJ, "scene.fps", "must be a number"),
    ("float for int", "[scene]\nframes = 10.0\n" + OBJ, "scene.frames", "must be an integer"),
    ("bool for int", "[solver]\ncg_iterations = true\n" + OBJ, "solver.cg_iterations", "integer"),
    ("number for bool", "[ground]\nenabled = 1\n" + OBJ, "ground.enabled", "true or false"),
    ("short vector", "[scene]\ngravity = [0, -9.81]\n" + OBJ, "scene.gravity", "3 numbers"),
    ("string in vector", OBJ + 'translate = [0, "1", 0]\n', "object[0] 'bunny': translate", "3 numbers"),
    ("young zero", OBJ + "young = 0\n", "object[0] 'bunny': young", "must be > 0 Pa, got 0"),
    ("young negative", OBJ + "young = -5.0\n", "object[0] 'bunny': young", "must be > 0 Pa, got -5.0"),
    ("poisson 0.5", OBJ + "poisson = 0.5\n", "object[0] 'bunny': poisson", ">= 0 and < 0.5"),
    ("poisson -0.1", OBJ + "poisson = -0.1\n", "object[0] 'bunny': poisson", "got -0.1"),
    ("density zero", OBJ + "density = 0\n", "object[0] 'bunny': density", "> 0 kg/m^3"),
    ("damping negative", OBJ + "damping_mass = -1\n", "object[0] 'bunny': damping_mass", ">= 0"),
    ("scale zero", OBJ + "scale = 0\n", "object[0] 'bunny': scale", "> 0"),
    ("subdivide 5", OBJ + "subdivide = 5\n", "object[0] 'bunny': subdivide", "in 0..4, got 5"),
    ("faces 99", OBJ + "faces = 99\n", "object[0] 'bunny': faces", "in 100..20000"),
    ("faces 20001", OBJ + "faces = 20001\n", "object[0] 'bunny': faces", "in 100..20000"),
    ("maxh 0", OBJ + "maxh = 0\n", "object[0] 'bunny': maxh", "> 0 and <= 1"),
    ("maxh above 1", OBJ + "maxh = 1.5\n", "object[0] 'bunny': maxh", "got 1.5"),
    ("fps zero", "[scene]\nfps = 0\n" + OBJ, "scene.fps", "must be > 0"),
    ("fps negative", "[scene]\nfps = -60.0\n" + OBJ, "scene.fps", "must be > 0"),
    ("substeps 0", "[scene]\nsubsteps = 0\n" + OBJ, "scene.substeps", ">= 1, got 0"),
    ("frames 0", "[scene]\nframes = 0\n" + OBJ, "scene.frames", ">= 1, got 0"),
    ("up axis X", '[scene]\nup_axis = "X"\n' + OBJ, "scene.up_axis", 'must be "Y" or "Z"'),
    ("cg_mode foo", '[solver]\ncg_mode = "foo"\n' + OBJ, "solver.cg_mode", '"tolerance" or "fixed"'),
    ("elements cubic", '[solver]\nelements = "cubic"\n' + OBJ, "solver.elements", '"linear" or "quadratic"'),
    ("elements 2", "[solver]\nelements = 2\n" + OBJ, "solver.elements", '"linear" or "quadratic", got 2'),
    ("cg_iterations 0", "[solver]\ncg_iterations = 0\n" + OBJ, "solver.cg_iterations", ">= 1"),
    ("cg_tolerance 1", "[solver]\ncg_tolerance = 1.0\n" + OBJ, "solver.cg_tolerance", "< 1"),
    ("cg_tolerance 0", "[solver]\ncg_tolerance = 0\n" + OBJ, "solver.cg_tolerance", "> 0"),
    ("contact_passes -1", "[solver]\ncontact_passes = -1\n" + OBJ, "solver.contact_passes", ">= 0"),
    ("contact_passes 1.5", "[solver]\ncontact_passes = 1.5\n" + OBJ, "solver.contact_passes", "integer"),
    ("rotation_updates -1", "[solver]\nrotation_updates = -1\n" + OBJ, "solver.rotation_updates", ">= 0"),
    ("rotation_updates 1.5", "[solver]\nrotation_updates = 1.5\n" + OBJ, "solver.rotation_updates", "integer"),
    ("rotation_tolerance -0.1", "[solver]\nrotation_tolerance = -0.1\n" + OBJ, "solver.rotation_tolerance", ">= 0"),
    ("rotation_tolerance nan", "[solver]\nrotation_tolerance = nan\n" + OBJ, "solver.rotation_tolerance", "finite"),
    ("static_lift 1", "[solver]\nstatic_lift = 1\n" + OBJ, "solver.static_lift", "true or false, got 1"),
    ("approach_limit < 0", "[collision]\napproach_limit = -0.01\n" + OBJ, "collision.approach_limit", ">= 0"),
    ("approach_limit 1", "[collision]\napproach_limit = 1.0\n" + OBJ, "collision.approach_limit", "< 1"),
    ("contact offset < 0", "[collision]\noffset = -0.001\n" + OBJ, "collision.offset", ">= 0"),
    ("contact offset 0.05", "[collision]\noffset = 0.05\n" + OBJ, "collision.offset", "< 0.05"),
    ("contact damping < 0", "[collision]\ndamping = -1.0\n" + OBJ, "collision.damping", ">= 0"),
    ("contact damping nan", "[collision]\ndamping = nan\n" + OBJ, "collision.damping", "finite"),
    ("contact damping inf", "[collision]\ndamping = inf\n" + OBJ, "collision.damping", "finite"),
    ("contact damping text", '[collision]\ndamping = "high"\n' + OBJ, "collision.damping", "a number"),
    ("ground stiffness 0", "[ground]\nstiffness = 0\n" + OBJ, "ground.stiffness", "> 0 1/s^2"),
    ("ground friction < 0", "[ground]\nfriction = -0.1\n" + OBJ, "ground.friction", ">= 0"),
    ("ground offset < 0", "[ground]\noffset = -0.001\n" + OBJ, "ground.offset", ">= 0 and <= 0.05"),
    ("ground offset 0.1", "[ground]\noffset = 0.1\n" + OBJ, "ground.offset", "<= 0.05"),
    (
        "obstacle offset 1",
        '[[obstacle]]\nkind = "sphere"\ncenter = [0, 0, 0]\nradius = 0.5\noffset = 1\n' + OBJ,
        "obstacle[0]: offset",
        "<= 0.05",
    ),
    (
        "missing mesh file",
        '[[object]]\nname = "a"\nmesh = "nowhere.obj"\n',
        "object[0] 'a': mesh",
        "file not found",
    ),
    ("unknown builtin", '[[object]]\nname = "a"\nmesh = "builtin:teapot"\n', "object[0] 'a': mesh", "teapot"),
    ("mesh missing", '[[object]]\nname = "a"\n', "object[0] 'a': mesh", "is required"),
    ("name missing", '[[object]]\nmesh = "builtin:bunny"\n', "object[0]: name", "is required"),
    ("duplicate names", OBJ + OBJ, "object[1] 'bunny': name", "already used by object[0]"),
    ("name with a space", '[[object]]\nname = "my bunny"\nmesh = "builtin:bunny"\n', "name", "USD prim"),
    ("name starting with digit", '[[object]]\nname = "1st"\nmesh = "builtin:bunny"\n', "name", "USD prim"),
    ("name not a string", '[[object]]\nname = 3\nmesh = "builtin:bunny"\n', "object[0]: name", "USD prim"),
    ("only pin_min", OBJ + "pin_min = [0, 0, 0]\n", "object[0] 'bunny': pin_max", "together with pin_min"),
    ("only pin_max", OBJ + "pin_max = [0, 0, 0]\n", "object[0] 'bunny': pin_min", "together with pin_max"),
    ("pin min > max", OBJ + "pin_min = [0, 2, 0]\npin_max = [1, 1, 1]\n", "pin_min", "<= pin_max"),
    ("nan value", OBJ + "young = nan\n", "object[0] 'bunny': young", "must be finite, got nan"),
    ("inf value", "[scene]\nfps = inf\n" + OBJ, "scene.fps", "must be finite"),
    ("nan in vector", OBJ + "velocity = [0, nan, 0]\n", "object[0] 'bunny': velocity", "finite"),
    ("toml syntax error", "[scene\nframes = 1\n", "TOML syntax error", "line 1"),
    ("no objects", "[scene]\nframes = 3\n", "object", "at least one [[object]]"),
    ("object as a table", '[object]\nname = "a"\nmesh = "builtin:bunny"\n', "object", "[[object]]"),
    ("scene not a table", "scene = 3\n" + OBJ, "scene", "must be a table"),
    ("collision stiffness 0", "[collision]\nstiffness = 0\n" + OBJ, "collision.stiffness", "> 0 1/s^2"),
    ("collision unknown key", "[collision]\nself = true\n" + OBJ, "collision.self", "not a known key"),
    ("self_collision not bool", OBJ + "self_collision = 1\n", "object[0] 'bunny': self_collision", "true or false"),
    ("collision_spacing < 0", OBJ + "collision_spacing = -0.1\n", "collision_spacing", ">= 0"),
    (
        "obstacle kind",
        '[[obstacle]]\nkind = "cone"\ncenter = [0, 0, 0]\n' + OBJ,
        "obstacle[0]: kind",
        '"sphere" or "box"',
    ),
    (
        "sphere without radius",
        '[[obstacle]]\nkind = "sphere"\ncenter = [0, 0, 0]\n' + OBJ,
        "obstacle[0]: radius",
        "required",
    ),
    ("sphere radius 0", '[[obstacle]]\nkind = "sphere"\ncenter = [0, 0, 0]\nradius = 0\n' + OBJ, "radius", "> 0"),
    ("box without extents", '[[obstacle]]\nkind = "box"\ncenter = [0, 0, 0]\n' + OBJ, "half_extents", "required"),
    (
        "box flat",
        '[[obstacle]]\nkind = "box"\ncenter = [0, 0, 0]\nhalf_extents = [1, 0, 1]\n' + OBJ,
        "obstacle[0]: half_extents",
        "> 0",
    ),
    ("obstacle missing center", '[[obstacle]]\nkind = "box"\n' + OBJ, "obstacle[0]: center", "is required"),
    ("camera fov 180", "[camera]\nfov = 180\n" + OBJ, "camera.fov", "< 180"),
    ("camera at target", "[camera]\nposition = [1, 1, 1]\ntarget = [1, 1, 1]\n" + OBJ, "camera.target", "differ"),
]


@pytest.mark.parametrize(("text", "key", "phrase"), [e[1:] for e in ERRORS], ids=[e[0] for e in ERRORS])
def test_error_is_one_line_naming_file_and_key(tmp_path, text, key, phrase):
    path = write(tmp_path, text)
    with pytest.raises(InputError) as info:
        load_scene(path)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"{path}: "), message
    assert key in message, message
    assert phrase in message, message


def test_obstacles_and_collision_keys_are_read(tmp_path):
    text = (
        "[collision]\nstiffness = 2e6\nfriction = 0.1\n"
        '[[obstacle]]\nkind = "sphere"\ncenter = [0, 1, 0]\nradius = 0.5\n'
        '[[obstacle]]\nkind = "box"\ncenter = [1, 0, 0]\nhalf_extents = [0.5, 0.25, 1]\nfriction = 0.0\n'
        + OBJ
        + "self_collision = true\ncollision_spacing = 0.01\n"
    )
    scene = load_scene(write(tmp_path, text))
    assert scene.collision == CollisionConfig(enabled=True, stiffness=2e6, friction=0.1)
    sphere, box = scene.obstacles
    assert (sphere.kind, sphere.center, sphere.radius) == ("sphere", (0.0, 1.0, 0.0), 0.5)
    assert (box.kind, box.half_extents, box.friction) == ("box", (0.5, 0.25, 1.0), 0.0)
    assert scene.objects[0].self_collision is True and scene.objects[0].collision_spacing == 0.01


def test_error_message_format_example(tmp_path):
    path = write(tmp_path, OBJ + "young = -5.0\n")
    with pytest.raises(InputError, match=r"^.*scene\.toml: object\[0\] 'bunny': young must be > 0 Pa, got -5\.0$"):
        load_scene(path)


def test_error_names_the_right_object(tmp_path):
    text = OBJ + '[[object]]\nname = "b"\nmesh = "builtin:bunny"\nyoung = -1.0\n'
    with pytest.raises(InputError, match=r"object\[1\] 'b': young"):
        load_scene(write(tmp_path, text))


def test_missing_scene_file(tmp_path):
    path = tmp_path / "absent.toml"
    with pytest.raises(InputError, match=r"absent\.toml: cannot read"):
        load_scene(path)


def test_relative_mesh_path_resolves_against_scene_folder(tmp_path, monkeypatch):
    (tmp_path / "meshes").mkdir()
    mesh = tmp_path / "meshes" / "thing.obj"
    mesh.write_text("v 0 0 0\n")
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    path = write(scenes, '[[object]]\nname = "a"\nmesh = "../meshes/thing.obj"\n')
    # The current directory must not matter: run from somewhere else.
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    scene = load_scene(path)
    assert Path(scene.objects[0].mesh) == mesh.resolve()
    assert Path(scene.objects[0].mesh).is_absolute()
    assert not scene.objects[0].is_builtin
    # The same relative path from the mesh folder's parent is not found relative to the scene.
    bad = write(tmp_path, '[[object]]\nname = "a"\nmesh = "../meshes/thing.obj"\n', "bad.toml")
    with pytest.raises(InputError, match="file not found"):
        load_scene(bad)


def test_absolute_mesh_path_kept(tmp_path):
    mesh = tmp_path / "m.obj"
    mesh.write_text("v 0 0 0\n")
    scene = load_scene(write(tmp_path, f'[[object]]\nname = "a"\nmesh = "{mesh}"\n'))
    assert scene.objects[0].mesh == str(mesh)


def test_mesh_directory_is_not_a_file(tmp_path):
    (tmp_path / "dir.obj").mkdir()
    with pytest.raises(InputError, match="file not found"):
        load_scene(write(tmp_path, '[[object]]\nname = "a"\nmesh = "dir.obj"\n'))


def test_default_scene_loads():
    path = default_scene_path()
    assert path.name == "default.toml" and path.is_file()
    scene = load_scene(path)
    assert (scene.frames, scene.fps, scene.substeps) == (120, 60.0, 4)
    assert scene.ground.enabled
    (bunny,) = scene.objects
    assert bunny.mesh == "builtin:bunny"
    assert (bunny.subdivide, bunny.faces, bunny.scale) == (2, 1000, 0.5)
    assert bunny.translate[1] == 1.0
    assert any(angle != 0.0 for angle in bunny.rotate)
    assert (bunny.young, bunny.poisson, bunny.density, bunny.damping_stiffness) == (2e5, 0.35, 1000.0, 0.005)


def test_with_frames_copies_and_validates(tmp_path):
    scene = load_scene(write(tmp_path, MINIMAL))
    short = scene.with_frames(7)
    assert short.frames == 7 and scene.frames == 120
    assert short.objects == scene.objects and short.dt == scene.dt
    with pytest.raises(InputError, match=r"scene\.frames must be >= 1, got 0"):
        scene.with_frames(0)
    with pytest.raises(InputError, match=r"scene\.frames must be an integer"):
        scene.with_frames(2.5)


def test_validate_on_hand_built_config(tmp_path):
    scene = Scene(path=tmp_path / "x.toml", objects=[ObjectConfig(name="a", mesh="builtin:bunny")])
    scene.validate()
    assert math.isclose(scene.dt, 1 / 240)
    scene.objects[0].poisson = 0.49
    scene.validate()
    scene.objects[0].young = float("inf")
    with pytest.raises(InputError, match=r"x\.toml: object\[0\] 'a': young must be finite"):
        scene.validate()


def test_quality_preset_fills_unset_keys_only(tmp_path):
    from warpfem.scene import PRESETS

    text = (
        '[solver]\nquality = "preview"\ncg_iterations = 7\n'
        + OBJ
        + '[[object]]\nname = "b"\nmesh = "builtin:bunny"\nfaces = 500\n'
    )
    scene = load_scene(write(tmp_path, text))
    preview = PRESETS["preview"]
    assert scene.substeps == preview["substeps"] and scene.solver.cg_mode == preview["cg_mode"]
    assert scene.solver.cg_iterations == 7  # set by the file: the file wins
    assert scene.objects[0].faces == preview["faces"] and scene.objects[0].maxh == preview["maxh"]
    assert scene.objects[1].faces == 500


def test_unknown_quality_preset_is_one_line(tmp_path):
    path = write(tmp_path, '[solver]\nquality = "ultra"\n' + OBJ)
    with pytest.raises(InputError, match=r"solver\.quality must be one of preview, default, high, got \"ultra\""):
        load_scene(path)

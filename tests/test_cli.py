"""The command line end to end: tiny scenes to USD, bad input, interruption."""

import json
import re
import subprocess
import sys

import numpy as np
import pytest
import trimesh
from pxr import Usd, UsdGeom, UsdValidation

import warpfem
from warpfem.build import euler_rotation
from warpfem.cli import main

SCENE = """
[scene]
frames = 6
substeps = 2
[solver]
cg_iterations = 60
cg_tolerance = 1e-5
[[object]]
name = "ball"
mesh = "ball.obj"
faces = 120
scale = 0.5
rotate = [10.0, 20.0, 30.0]
translate = [0.0, 0.6, 0.0]
young = 1e5
"""


@pytest.fixture
def scene_dir(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=3)  # 1,280 triangles, radius 1
    sphere.export(tmp_path / "ball.obj")
    (tmp_path / "scene.toml").write_text(SCENE)
    return tmp_path


def _run(args):
    return main([str(a) for a in args])


def _one_line_error(capsys, *needles):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("warpfem: error: ")
    for needle in needles:
        assert needle in err[0], err[0]


def _stage_points(path, prim="/World/ball"):
    stage = Usd.Stage.Open(str(path))
    attr = UsdGeom.Mesh(stage.GetPrimAtPath(prim)).GetPointsAttr()
    return stage, attr, [np.array(attr.Get(t)) for t in attr.GetTimeSamples()]


def test_run_writes_valid_usd_matching_the_simulation(scene_dir, device, capsys):
    out = scene_dir / "anim.usdc"
    assert _run(["run", scene_dir / "scene.toml", "--out", out, "--device", device, "--no-cache", "--quiet"]) == 0
    summary = capsys.readouterr().out
    assert "frames" in summary and "tets" in summary and "dense triangles" in summary
    penetration = next(line for line in summary.splitlines() if line.startswith("penetration"))
    assert "bodies - (a single body); below the ground" in penetration  # no figure for a check never made
    cg = next(line for line in summary.splitlines() if line.startswith("CG iterations"))
    assert "every solve within its tolerance before its cap" in cg  # 60 iterations reach 1e-5 on a ball
    stage, attr, frames = _stage_points(out)
    assert len(frames) == 7 and stage.GetEndTimeCode() == 6  # frame 0 (initial pose) plus 6 frames
    ctx = UsdValidation.ValidationContext(UsdValidation.ValidationRegistry().GetOrLoadAllValidators())
    errors = [e for e in ctx.Validate(stage) if e.GetType() == UsdValidation.ValidationErrorType.Error]
    assert errors == []

    # frame 0 is the input mesh placed by the scene transform (an independent reference)
    sphere = trimesh.load(scene_dir / "ball.obj", process=False)
    placed = 0.5 * sphere.vertices @ euler_rotation((10.0, 20.0, 30.0)).T + [0.0, 0.6, 0.0]
    assert frames[0].shape == placed.shape
    np.testing.assert_allclose(np.sort(frames[0], axis=0), np.sort(placed, axis=0), atol=1e-5)

    # the API's dense points after the same frames are the file's last frame
    scene = warpfem.load_scene(scene_dir / "scene.toml")
    sim = warpfem.Simulation(scene, device=device, cache=False)
    for _ in range(scene.frames):
        sim.step_frame()
    assert sim.frame == scene.frames and sim.time == pytest.approx(scene.frames / scene.fps)
    np.testing.assert_allclose(frames[-1], sim.dense_points("ball"), atol=1e-6)
    # and NumPy's barycentric map of the final tet positions
    obj = scene.objects[0]
    body = warpfem.prepare(obj.mesh, faces=obj.faces, maxh=obj.maxh)
    x = sim.tet_points("ball")
    expected = np.einsum("nk,nkd->nd", body.embed_bary, x[body.tets[body.embed_tet]])
    np.testing.assert_allclose(frames[-1], expected, atol=1e-4)
    assert frames[-1][:, 1].mean() < frames[0][:, 1].mean()  # it fell


@pytest.mark.parametrize(
    "edit, needles",
    [
        ("young = 1e5", ("young", "> 0", "-3")),
        ("faces = 120", ("facez", "not a known key")),
        ('mesh = "ball.obj"', ("missing.obj",)),
        ("poisson = 0.3", ("poisson",)),
    ],
)
def test_bad_scene_is_one_line_exit_2_and_no_output(scene_dir, capsys, edit, needles):
    replacement = {
        "young = 1e5": "young = -3.0",
        "faces = 120": "facez = 120",
        'mesh = "ball.obj"': 'mesh = "missing.obj"',
        "poisson = 0.3": "poisson = 0.5",
    }[edit]
    text = SCENE if edit in SCENE else SCENE + edit + "\n"
    (scene_dir / "scene.toml").write_text(text.replace(edit, replacement))
    out = scene_dir / "anim.usdc"
    assert _run(["run", scene_dir / "scene.toml", "--out", out, "--device", "cpu", "--no-cache"]) == 2
    _one_line_error(capsys, "scene.toml", *needles)
    assert sorted(p.name for p in scene_dir.iterdir()) == ["ball.obj", "scene.toml"]


def test_a_collision_spacing_asking_millions_of_points_is_one_line_exit_2(scene_dir, capsys, monkeypatch):
    """A spacing in metres far below the body's size (the ball, 1 m across, at 0.1 mm: its 3.1 m^2 of surface
    over (1e-4 m)^2 is about 3.1e8 points) stops before any point is chosen and before any kernel is compiled
    (on a fresh machine the user sees the one line, not the compiler's notices first), naming the key, the
    object and the least spacing that would do (sqrt(3.1 m^2 / 1e6) = 1.8 mm)."""

    def no_compile(*args, **kwargs):
        raise AssertionError("kernels loaded before the scene's collision spacing was checked")

    monkeypatch.setattr("warpfem.simulation.load_modules", no_compile)
    (scene_dir / "scene.toml").write_text(SCENE.replace("scale = 0.5", "scale = 0.5\ncollision_spacing = 1e-4"))
    out = scene_dir / "anim.usdc"
    assert _run(["run", scene_dir / "scene.toml", "--out", out, "--device", "cpu", "--no-cache"]) == 2
    needles = ("scene.toml", "object 'ball'", "collision_spacing = 0.0001 m", "at most 1,000,000", "0.0018 m")
    _one_line_error(capsys, *needles)
    assert sorted(p.name for p in scene_dir.iterdir()) == ["ball.obj", "scene.toml"]


@pytest.mark.parametrize("defect", ["hole", "nan", "flat", "empty"])
def test_bad_mesh_is_one_line_exit_2_and_no_output(scene_dir, capsys, defect):
    mesh = trimesh.creation.icosphere(subdivisions=2)
    path = scene_dir / "ball.obj"
    if defect == "hole":  # an open bowl: far too large a hole to close
        keep = mesh.vertices[mesh.faces].mean(axis=1)[:, 1] < 0.3
        trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False).export(path)
    elif defect == "nan":
        v = mesh.vertices.copy()
        v[5] = np.nan
        path.write_text(
            "".join(f"v {a} {b} {c}\n" for a, b, c in v)
            + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in mesh.faces)
        )
    elif defect == "flat":
        v = mesh.vertices.copy()
        v[:, 2] = 0.0
        trimesh.Trimesh(v, mesh.faces, process=False).export(path)
    else:
        path.write_text("")
    out = scene_dir / "anim.usdc"
    assert _run(["run", scene_dir / "scene.toml", "--out", out, "--device", "cpu", "--no-cache"]) == 2
    _one_line_error(capsys, "ball.obj")
    assert sorted(p.name for p in scene_dir.iterdir()) == ["ball.obj", "scene.toml"]


def test_bad_options_exit_2(scene_dir, capsys):
    scene = scene_dir / "scene.toml"
    assert _run(["run", scene, "--frames", "0"]) == 2
    _one_line_error(capsys, "--frames")
    assert _run(["run", scene, "--out", scene_dir / "anim.obj"]) == 2
    _one_line_error(capsys, ".usdc")
    assert _run(["run", scene, "--out", scene_dir / "no" / "anim.usdc"]) == 2
    _one_line_error(capsys, "does not exist")
    assert _run(["run", scene, "--device", "tpu:3"]) == 2
    _one_line_error(capsys, "tpu:3")
    assert _run(["prepare", scene_dir / "nothere.obj"]) == 2
    _one_line_error(capsys, "nothere.obj")


def test_interrupted_run_keeps_the_frames_done(scene_dir, capsys, monkeypatch):
    import warpfem.simulation as simulate

    calls = {"n": 0}
    original = simulate.Simulation.advance

    def advance(self, timer=None):
        calls["n"] += 1
        if calls["n"] == 4:
            raise KeyboardInterrupt
        original(self, timer)

    monkeypatch.setattr(simulate.Simulation, "advance", advance)
    out = scene_dir / "anim.usdc"
    assert _run(["run", scene_dir / "scene.toml", "--out", out, "--device", "cpu", "--no-cache", "--quiet"]) == 130
    assert "interrupted" in capsys.readouterr().err
    stage, _, frames = _stage_points(out)
    assert len(frames) == 4 and stage.GetEndTimeCode() == 3


def test_prepare_reports_what_it_made(scene_dir, capsys):
    """Every statistic of ``--json`` is in the text report, worded, with the mesh's own size and counts."""
    assert _run(["prepare", scene_dir / "ball.obj", "--faces", "200", "--no-cache", "--json"]) == 0
    stats = json.loads(capsys.readouterr().out)
    assert _run(["prepare", scene_dir / "ball.obj", "--faces", "200", "--no-cache"]) == 0
    rows = dict(re.split(r"\s{2,}", line, maxsplit=1) for line in capsys.readouterr().out.splitlines())
    sphere = trimesh.load(scene_dir / "ball.obj", process=False)  # the file read independently
    diagonal = np.linalg.norm(np.ptp(sphere.vertices, axis=0))
    assert rows["size"].startswith(f"bounding-box diagonal {diagonal:.4g} ")
    assert rows["dense surface"].startswith(f"{len(sphere.vertices):,} vertices, {len(sphere.faces):,} triangles")
    assert rows["tets"].startswith(f"{stats['tets']:,} on {stats['tet_vertices']:,} vertices")
    assert rows["embedding"].startswith(f"{100 * stats['embedding_coverage']:.2f} % of dense vertices inside a tet")
    outside = stats["embedding_outside_max"]
    assert f"at most {outside:.4g} ({100 * outside / diagonal:.2f} %) outside theirs" in rows["embedding"]
    hausdorff = stats["hausdorff"]
    assert rows["hausdorff"].startswith(f"{hausdorff:.4g} ({100 * hausdorff / diagonal:.2f} %)")
    assert rows["cache"] == "off" and "hausdorff" in rows["seconds"]
    assert [label for label in rows if "_" in label] == []  # no statistic left unworded


def test_prepare_report_words_sizing_and_lists_what_it_does_not_word(scene_dir):
    """A thickness-sized body gets a sizing row; a statistic the report does not know is still listed."""
    from warpfem.cli.prepare import report_rows

    stats = dict(warpfem.prepare(scene_dir / "ball.obj", faces=200, cache_dir=None).stats)
    stats.update(thickness=0.05, thickness_relative=0.025, tets_across=3, max_tets=3000, sizing_capped=1, new=2.5)
    rows = dict(report_rows(stats, diagonal=2.0))
    assert rows["sizing"] == "thinnest part 0.05 (2.50 %), 3 tets across it, budget 3,000 tets, capped by the budget"
    assert rows["new"] == "2.5"


@pytest.mark.slow
def test_default_scene_runs_from_a_fresh_process(tmp_path):
    """The README's first command, shortened: the shipped default scene (>= 100k dense triangles)."""
    out = tmp_path / "default.usdc"
    cmd = [
        sys.executable,
        "-m",
        "warpfem",
        "run",
        "--frames",
        "2",
        "--out",
        str(out),
        "--device",
        "cpu",
        "--cache-dir",
        str(tmp_path / "cache"),
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    triangles = int(next(line for line in done.stdout.splitlines() if line.startswith("dense triangles")).split()[-3])
    assert triangles >= 100_000
    _, _, frames = _stage_points(out, "/World/bunny")
    assert len(frames) == 3


def test_prepare_options_reach_the_pipeline(scene_dir, capsys):
    assert (
        _run(
            [
                "prepare",
                scene_dir / "ball.obj",
                "--faces",
                "200",
                "--no-cache",
                "--shells",
                "largest",
                "--max-hole",
                "0.1",
                "--timeout",
                "60",
            ]
        )
        == 0
    )
    assert "tets" in capsys.readouterr().out
    for bad, needle in (
        (["--shells", "bogus"], "--shells"),
        (["--timeout", "0"], "--timeout"),
        (["--max-hole", "-1"], "--max-hole"),
        (["--tets-across", "65"], "--tets-across"),
        (["--tets-across", "nan"], "--tets-across"),
        (["--max-tets", "50"], "--max-tets"),
    ):
        assert _run(["prepare", scene_dir / "ball.obj", "--no-cache", *bad]) == 2
        _one_line_error(capsys, needle)


def test_prepare_sizes_by_thickness_as_a_scene_would(scene_dir, capsys):
    """``--tets-across`` and ``--max-tets`` make the body the scene keys make: the API's tets, more across the
    ball for more tets across it, and fewer where the budget caps them."""

    def tets(across: str, budget: str) -> dict:
        args = ["prepare", scene_dir / "ball.obj", "--no-cache", "--json", "--faces", "100", "--maxh", "1"]
        assert _run([*args, "--tets-across", across, "--max-tets", budget]) == 0
        return json.loads(capsys.readouterr().out)

    three, six, capped = tets("3", "100000"), tets("6", "100000"), tets("6", "200")
    body = warpfem.prepare(scene_dir / "ball.obj", faces=100, maxh=1.0, across=6.0, max_tets=100_000, cache_dir=None)
    assert six["tets"] == body.stats["tets"] and six["tets_across"] == 6 and six["max_tets"] == 100_000
    assert three["tets"] < six["tets"] and not six["sizing_capped"]
    assert capped["sizing_capped"] == 1 and capped["tets"] < six["tets"]
    # --quality fills what is not given from the scene preset; what is given wins
    assert _run(["prepare", scene_dir / "ball.obj", "--no-cache", "--json", "--quality", "default"]) == 0
    preset = json.loads(capsys.readouterr().out)
    body = warpfem.prepare(scene_dir / "ball.obj", faces=1000, maxh=0.2, across=2.0, max_tets=3000, cache_dir=None)
    assert (preset["tets_across"], preset["max_tets"], preset["tets"]) == (2, 3000, body.stats["tets"])
    assert tets("3", "100000")["tets_across"] == 3 and _run(["prepare", "x.obj", "--quality", "best"]) == 2
    _one_line_error(capsys, "--quality", "invalid choice")


def _warnings(scene_dir, text: str, capsys, needle: str, frames: int) -> list[str]:
    """The stderr lines holding ``needle`` of a CPU run of scene ``text`` for ``frames`` frames."""
    (scene_dir / "w.toml").write_text(text)
    args = ["run", scene_dir / "w.toml", "--out", scene_dir / "w.usdc", "--device", "cpu", "--no-cache"]
    assert _run([*args, "--frames", str(frames)]) == 0
    return [line for line in capsys.readouterr().err.splitlines() if needle in line]


def test_fast_bodies_warn_once_about_tunnelling(scene_dir, capsys):
    text = SCENE.replace("substeps = 2", "substeps = 1") + (
        '[[object]]\nname = "other"\nmesh = "ball.obj"\nfaces = 120\nscale = 0.5\ntranslate = [0.0, 0.6, 3.0]\n'
        "velocity = [0.0, 0.0, -90.0]\n"
    )
    warnings = _warnings(scene_dir, text, capsys, "may pass through", frames=3)
    assert len(warnings) == 1 and "'other'" in warnings[0] and "raise substeps" in warnings[0]


def test_bodies_placed_inside_one_another_are_named_once(scene_dir, capsys):
    """Two balls placed a tenth of their diameter into each other (and one clear of both): one warning naming the
    two, and not the third."""
    text = SCENE + (
        '[[object]]\nname = "into"\nmesh = "ball.obj"\nfaces = 120\nscale = 0.5\ntranslate = [0.0, 1.5, 0.0]\n'
        '[[object]]\nname = "clear"\nmesh = "ball.obj"\nfaces = 120\nscale = 0.5\ntranslate = [3.0, 0.6, 0.0]\n'
    )
    warnings = _warnings(scene_dir, text, capsys, "start inside", frames=2)
    assert len(warnings) == 1 and "'ball'" in warnings[0] and "'into'" in warnings[0]
    assert "'clear'" not in warnings[0]


def test_fast_rotation_warns_once(scene_dir, capsys, monkeypatch):
    import warpfem.simulation as simulate

    monkeypatch.setattr(simulate, "FAST_TURN", 0.0)  # any turn counts: the warning's plumbing
    out = scene_dir / "spin.usdc"
    assert _run(["run", scene_dir / "scene.toml", "--out", out, "--device", "cpu", "--no-cache", "--frames", "4"]) == 0
    warnings = [line for line in capsys.readouterr().err.splitlines() if "rad per step" in line]
    assert len(warnings) == 1 and "'ball'" in warnings[0] and "raise substeps" in warnings[0]

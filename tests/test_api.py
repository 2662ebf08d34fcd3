"""The public Python API, the README's example, the package's layering and its lint."""

import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

import warpfem

ROOT = Path(__file__).resolve().parents[1]

SCENE = {
    "scene": {"frames": 3, "substeps": 2},
    "object": [
        {"name": "ball", "mesh": "ball.obj", "faces": 120, "translate": [0.0, 0.35, 0.0], "scale": 0.15},
        {"name": "top", "mesh": "ball.obj", "faces": 120, "translate": [0.05, 0.9, 0.0], "scale": 0.15},
    ],
}


def _tool(name: str) -> str:
    """A console script installed beside this Python (the test extra's), else on PATH."""
    beside = Path(sys.executable).with_name(name)
    found = str(beside) if beside.exists() else shutil.which(name)
    if found is None:
        pytest.fail(f"{name} is not installed: pip install -e '.[test]'")
    return found


def test_layers_follow_the_import_contracts():
    """prep, sim, io, cli and the kernels import only what their layer may (pyproject's contracts)."""
    done = subprocess.run([_tool("lint-imports"), "--no-cache"], cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    assert "0 broken" in done.stdout


def test_code_is_ruff_clean():
    done = subprocess.run([_tool("ruff"), "check", "--no-cache", "."], cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout[-3000:]


def test_no_source_file_runs_past_800_lines():
    files = [*ROOT.glob("warpfem/**/*.py"), *ROOT.glob("kernels/*.py"), *ROOT.glob("scripts/*.py")]
    long = {str(p.relative_to(ROOT)): n for p in files if (n := len(p.read_text().splitlines())) > 800}
    assert long == {}


def _expanded(pattern: str) -> list[str]:
    """``pattern`` with each ``{a,b}`` alternative written out, as a shell expands it."""
    match = re.search(r"\{([^{}]*)\}", pattern)
    if match is None:
        return [pattern]
    head, tail = pattern[: match.start()], pattern[match.end() :]
    return [name for alt in match.group(1).split(",") for name in _expanded(head + alt + tail)]


def test_every_result_file_is_cited():
    """scripts/results keeps only what BENCHMARKS.md, the READMEs and docs/ name (a file, a folder, or a glob
    such as ``ab-x-*.json``; a log counts with the JSON it sits beside), and holds every file they name."""
    import fnmatch

    pages = [ROOT / "BENCHMARKS.md", ROOT / "README.md", ROOT / "scenes" / "README.md", *ROOT.glob("docs/*.md")]
    text = "\n".join(p.read_text() for p in pages)
    files = re.findall(r"[\w.*{},\-]+\.(?:json|csv|png|txt)", text)
    folders = re.findall(r"`scripts/results/([\w.\-]+)/`", text)
    patterns = {name for token in files + folders for name in _expanded(token)}
    uncited = []
    for path in sorted((ROOT / "scripts" / "results").iterdir()):
        name = path.with_suffix(".json").name if path.suffix == ".log" else path.name
        if not any(fnmatch.fnmatch(name, p) for p in patterns):
            uncited.append(path.name)
    assert uncited == []
    cited = re.findall(r"scripts/results/([\w.*,\-]+\.(?:json|csv|png|txt))", text)
    present = [p.name for p in (ROOT / "scripts" / "results").iterdir()]
    assert [name for name in cited if not fnmatch.filter(present, name)] == []  # and nothing cited is missing


@pytest.fixture
def ball_dir(tmp_path):
    trimesh.creation.icosphere(subdivisions=2).export(tmp_path / "ball.obj")
    return tmp_path


def test_scene_from_dict_resolves_meshes_against_base_dir(ball_dir):
    scene = warpfem.Scene.from_dict(SCENE, base_dir=ball_dir)
    assert [o.name for o in scene.objects] == ["ball", "top"]
    assert Path(scene.objects[0].mesh) == (ball_dir / "ball.obj").resolve()
    assert scene.frames == 3 and scene.substeps == 2 and scene.dt == pytest.approx(1 / 120)
    assert SCENE["object"][0]["mesh"] == "ball.obj"  # the caller's dict is left as it was


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda d: d["scene"].update(frames=0), "scene.frames"),
        (lambda d: d["object"][0].update(young=-1.0), "object[0] 'ball': young"),
        (lambda d: d["object"][1].update(colour="red"), "colour is not a known key"),
        (lambda d: d.update(objects=[{"name": "x"}]), "objects is not a known table (did you mean object?)"),
    ],
)
def test_scene_from_dict_rejects_like_a_file(ball_dir, change, message):
    """The same one-line messages and error type as a scene file with the same content."""
    import copy

    doc = copy.deepcopy(SCENE)
    change(doc)
    with pytest.raises(warpfem.InputError) as from_dict:
        warpfem.Scene.from_dict(doc, base_dir=ball_dir, name="scene.toml")
    assert message in str(from_dict.value) and "\n" not in str(from_dict.value)
    toml = ball_dir / "scene.toml"
    toml.write_text(_toml(doc))
    with pytest.raises(warpfem.InputError) as from_file:
        warpfem.load_scene(toml)
    assert str(from_file.value) == str(from_dict.value)


def _toml(doc: dict) -> str:
    """A minimal TOML writer for the scene dicts above (tables of scalars and lists, arrays of tables)."""

    def value(v):
        if isinstance(v, str):
            return f'"{v}"'
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return repr(v)

    lines = []
    for key, table in doc.items():
        for entry in table if isinstance(table, list) else [table]:
            lines.append(f"[[{key}]]" if isinstance(table, list) else f"[{key}]")
            lines += [f"{k} = {value(v)}" for k, v in entry.items()]
    return "\n".join(lines) + "\n"


def test_simulation_steps_frames_and_reports(ball_dir):
    scene = warpfem.Scene.from_dict(SCENE, base_dir=ball_dir)
    sim = warpfem.Simulation(scene, device="cpu", cache_dir=ball_dir / "cache")
    assert sim.body_names == ["ball", "top"] and sim.frame == 0 and sim.time == 0.0
    rest = sim.dense_points("top")
    sphere = trimesh.load(ball_dir / "ball.obj", process=False)
    np.testing.assert_allclose(
        np.sort(rest, axis=0), np.sort(0.15 * sphere.vertices + [0.05, 0.9, 0.0], axis=0), atol=1e-5
    )
    for _ in range(scene.frames):
        stats = sim.step_frame()
    assert sim.frame == 3 and sim.time == pytest.approx(3 / 60)
    assert stats is sim.stats and stats.cg_iterations > 0 and stats.cg_residual <= scene.solver.cg_tolerance
    # free fall for 3 frames (no contact yet): the drop is about g t^2 / 2 (implicit Euler lags slightly)
    drop = rest[:, 1].mean() - sim.dense_points("top")[:, 1].mean()
    assert 0.5 * 9.81 * sim.time**2 * 0.8 < drop < 0.5 * 9.81 * sim.time**2 * 1.2
    tets = sim.tet_points("top")
    assert tets.shape == (sim.model.bodies[1].vertex_count, 3)
    top = sim.model.bodies[1]
    np.testing.assert_array_equal(tets, sim.state().x.numpy()[top.vertex_start : top.vertex_start + top.vertex_count])
    for name, points in zip(sim.body_names, sim.dense_points(), strict=True):  # a body's own, as all at once
        np.testing.assert_array_equal(sim.dense_points(name), points)
    assert isinstance(sim.state(), warpfem.State) and isinstance(sim.solver, warpfem.Solver)
    with pytest.raises(warpfem.InputError, match="no body named 'nope'.*ball, top"):
        sim.dense_points("nope")


@pytest.mark.slow
def test_readme_python_example_runs_as_written(tmp_path, monkeypatch):
    """The first python block of README.md, run from a copy of the repository's scenes (it writes bunny.usdc)."""
    code = re.search(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S).group(1)
    shutil.copytree(ROOT / "scenes", tmp_path / "scenes")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("WARPFEM_CACHE", str(tmp_path / "cache"))
    done = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(tmp_path / "bunny.usdc"))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/bunny"))
    assert stage.GetEndTimeCode() == 30 and len(mesh.GetPointsAttr().Get(30)) > 90_000


@pytest.mark.parametrize("cache", [True, False])
def test_a_run_preprocesses_each_mesh_once(ball_dir, monkeypatch, cache):
    """Two bodies of one mesh and one of another: two preprocessing passes, cached or not."""
    import warpfem.build as build
    from warpfem.cli import main

    trimesh.creation.box(extents=(0.2, 0.2, 0.2)).export(ball_dir / "box.obj")
    doc = {**SCENE, "object": [*SCENE["object"], {"name": "box", "mesh": "box.obj", "translate": [0.6, 0.3, 0.0]}]}
    (ball_dir / "scene.toml").write_text(_toml(doc))
    calls = []
    real = build.prepare
    monkeypatch.setattr(build, "prepare", lambda mesh, **kw: calls.append(Path(mesh).name) or real(mesh, **kw))
    flags = ["--cache-dir", str(ball_dir / "cache")] if cache else ["--no-cache"]
    args = ["run", str(ball_dir / "scene.toml"), "--out", str(ball_dir / "a.usdc"), "--device", "cpu", "--quiet"]
    assert main([*args, "--frames", "1", *flags]) == 0
    assert sorted(calls) == ["ball.obj", "box.obj"]
    assert (ball_dir / "cache").exists() == cache


def test_run_reports_the_penetration_a_check_of_the_file_finds(tmp_path, device):
    """The summary's ground figure is the lowest dense point of the written file over all frames (NumPy), its last
    body figure libigl's check of the written last frame, and every extent the written points' bounds."""
    import igl
    from pxr import Usd, UsdGeom

    scene = warpfem.load_scene(ROOT / "tests" / "data" / "golden" / "two_balls.toml")
    summary = warpfem.run(scene, out=tmp_path / "a.usdc", device=device, cache=False)
    stage = Usd.Stage.Open(str(tmp_path / "a.usdc"))
    lowest, lowest_by_frame, last = {}, {}, {}
    for name in ("ball", "top"):
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath(f"/World/{name}"))
        frames = [np.asarray(mesh.GetPointsAttr().Get(t)) for t in range(scene.frames + 1)]
        for t, points in enumerate(frames):  # the extent the device reduced is the points' bounds
            np.testing.assert_array_equal(mesh.GetExtentAttr().Get(t), [points.min(axis=0), points.max(axis=0)])
        lowest_by_frame[name] = [points[:, 1].min() for points in frames]
        lowest[name] = min(lowest_by_frame[name])
        last[name] = (frames[-1].astype(np.float64), np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3))
    below = max(0.0, -min(lowest.values()))
    deepest = 0.0  # the last frame's bodies in each other, by libigl's exact winding numbers and distances
    for inner, outer in (("ball", "top"), ("top", "ball")):
        (q, _), (v, f) = last[inner], last[outer]
        inside = q[igl.winding_number(v, f, q) > 0.5]
        if len(inside):
            depth, *_ = igl.signed_distance(inside, v, f, sign_type=igl.SIGNED_DISTANCE_TYPE_UNSIGNED)
            deepest = max(deepest, float(np.abs(depth).max()) / np.linalg.norm(np.ptp(v, axis=0)))
    assert summary.penetration_end.relative == pytest.approx(deepest, abs=1e-5)
    assert summary.penetration.below_ground == pytest.approx(below, abs=1e-7)
    # the frame it names is the first written frame that low (-1 where nothing went below the ground)
    per_frame = np.min([lows for lows in lowest_by_frame.values()], axis=0)
    first = int(np.flatnonzero(per_frame <= -below + 1e-7)[0]) if below > 0.0 else -1
    assert summary.penetration.below_frame == first
    assert summary.penetration_end.below_ground <= summary.penetration.below_ground
    assert summary.penetration_frames >= 1 and summary.penetration.relative >= summary.penetration_end.relative
    assert summary.penetration.inside in ("", "ball in top", "top in ball")


def test_run_names_the_frame_its_surfaces_sank_deepest_below_the_ground(tmp_path, device):
    """On a soft ground with the penalties alone (no lift out of it), the balls' written dense points go below the
    ground; the summary's ground figure names the first written frame as low as the lowest (NumPy on the file)."""
    import dataclasses

    from pxr import Usd, UsdGeom

    scene = warpfem.load_scene(ROOT / "tests" / "data" / "golden" / "two_balls.toml")
    scene = dataclasses.replace(
        scene,
        ground=dataclasses.replace(scene.ground, stiffness=3e3),
        solver=dataclasses.replace(scene.solver, static_lift=False),
    )
    summary = warpfem.run(scene, out=tmp_path / "a.usdc", device=device, cache=False)
    stage = Usd.Stage.Open(str(tmp_path / "a.usdc"))
    lows = np.min(
        [
            [np.asarray(UsdGeom.Mesh(stage.GetPrimAtPath(f"/World/{name}")).GetPointsAttr().Get(t))[:, 1].min()
             for t in range(scene.frames + 1)]
            for name in ("ball", "top")
        ],
        axis=0,
    )  # fmt: skip
    assert lows.min() < -1e-3  # the soft ground let them sink
    worst = summary.penetration
    assert worst.below_ground == pytest.approx(-lows.min(), abs=1e-7)
    assert worst.below_frame == int(np.flatnonzero(lows <= lows.min() + 1e-7)[0])


def test_run_body_check_at_the_end_is_a_check_of_the_written_last_frame(tmp_path, device):
    """Two balls started inside each other: the summary's last body figure, measured on the device a check
    behind the run, is libigl's exact check of the written last frame (winding numbers and distances)."""
    import dataclasses

    import igl
    from pxr import Usd, UsdGeom

    scene = warpfem.load_scene(ROOT / "tests" / "data" / "golden" / "two_balls.toml")
    top = dataclasses.replace(scene.objects[1], translate=(0.05, 0.48, 0.0))
    scene = dataclasses.replace(scene, objects=[scene.objects[0], top]).with_frames(2)
    summary = warpfem.run(scene, out=tmp_path / "a.usdc", device=device, cache=False)
    stage = Usd.Stage.Open(str(tmp_path / "a.usdc"))
    last = {}
    for name in ("ball", "top"):
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath(f"/World/{name}"))
        faces = np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
        last[name] = (np.asarray(mesh.GetPointsAttr().Get(scene.frames), np.float64), faces)
    deepest, inside = 0.0, ""
    for inner, outer in (("ball", "top"), ("top", "ball")):
        (q, _), (v, f) = last[inner], last[outer]
        held = q[igl.winding_number(v, f, q) > 0.5]
        if len(held):
            depth, *_ = igl.signed_distance(held, v, f, sign_type=igl.SIGNED_DISTANCE_TYPE_UNSIGNED)
            relative = float(np.abs(depth).max()) / np.linalg.norm(np.ptp(v, axis=0))
            if relative > deepest:
                deepest, inside = relative, f"{inner} in {outer}"
    assert deepest > 0.01  # still well inside each other
    assert summary.penetration_end.relative == pytest.approx(deepest, abs=1e-5)
    assert summary.penetration_end.inside == inside and summary.penetration_end.frame == scene.frames
    # the worst over the run names a frame it checked, and libigl finds that depth in that written frame
    worst, seen = summary.penetration, 0.0
    for inner, outer in (("ball", "top"), ("top", "ball")):
        at = {}
        for name in (inner, outer):
            mesh = UsdGeom.Mesh(stage.GetPrimAtPath(f"/World/{name}"))
            faces = np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
            at[name] = (np.asarray(mesh.GetPointsAttr().Get(worst.frame), np.float64), faces)
        (q, _), (v, f) = at[inner], at[outer]
        held = q[igl.winding_number(v, f, q) > 0.5]
        if len(held):
            depth, *_ = igl.signed_distance(held, v, f, sign_type=igl.SIGNED_DISTANCE_TYPE_UNSIGNED)
            seen = max(seen, float(np.abs(depth).max()) / np.linalg.norm(np.ptp(v, axis=0)))
    assert 1 <= worst.frame <= scene.frames and worst.relative == pytest.approx(seen, abs=1e-5)


def test_cg_stopping_at_its_cap_is_said_once_and_counted(ball_dir, capsys):
    """Three iterations cannot reach 1e-6 on a landing ball: one warning, and the summary counts the frames."""
    from warpfem.cli import main

    doc = {**SCENE, "scene": {"frames": 4, "substeps": 2}, "solver": {"cg_iterations": 3, "cg_tolerance": 1e-6}}
    (ball_dir / "capped.toml").write_text(_toml(doc))
    args = ["run", str(ball_dir / "capped.toml"), "--out", str(ball_dir / "c.usdc"), "--device", "cpu", "--json"]
    assert main(args) == 0
    captured = capsys.readouterr()
    warnings = [line for line in captured.err.splitlines() if "stopped at its cap of 3 iterations" in line]
    assert len(warnings) == 1 and "cg_iterations" in warnings[0]
    import json

    summary = json.loads(captured.out)
    assert summary["cg_capped_frames"] == 4 and summary["cg_residual_max"] > 1e-6
    # every solve of every step stopped short (three iterations reach 1e-6 nowhere)
    assert summary["cg_short_solves"] == round(summary["cg_solves_per_step"] * 8) >= 8
    doc["solver"] = {"cg_iterations": 200, "cg_tolerance": 1e-6}  # enough iterations: nothing said
    (ball_dir / "capped.toml").write_text(_toml(doc))
    assert main([*args, "--overwrite"]) == 0
    captured = capsys.readouterr()
    assert "stopped at its cap" not in captured.err and json.loads(captured.out)["cg_capped_frames"] == 0
    assert json.loads(captured.out)["cg_short_solves"] == 0


def test_angular_velocity_spins_the_body_about_its_centre_of_mass(ball_dir):
    """The initial state's momentum is the body's mass times its velocity and its angular momentum about the
    centre of mass is I w (NumPy, from the lumped masses), the spin's axis and rate as given."""
    omega, v0 = np.array([0.0, 0.0, 12.0]), np.array([1.0, 0.0, 0.0])
    doc = {
        "scene": {"frames": 1},
        "object": [{**SCENE["object"][1], "velocity": list(v0), "angular_velocity": list(omega)}],
    }
    sim = warpfem.Simulation(warpfem.Scene.from_dict(doc, base_dir=ball_dir), device="cpu", cache=False)
    x, v, m = sim.state().x.numpy(), sim.state().v.numpy(), sim.model.mass.numpy()
    centre = (m[:, None] * x).sum(0) / m.sum()
    r = x - centre
    np.testing.assert_allclose((m[:, None] * v).sum(0), m.sum() * v0, rtol=1e-5, atol=1e-6)
    inertia = (m[:, None, None] * ((r * r).sum(1)[:, None, None] * np.eye(3) - r[:, :, None] * r[:, None, :])).sum(0)
    momentum = (m[:, None] * np.cross(r, v)).sum(0)
    np.testing.assert_allclose(momentum, inertia @ omega, rtol=1e-4, atol=1e-7)
    with pytest.raises(warpfem.InputError, match="angular_velocity"):
        warpfem.Scene.from_dict(
            {**doc, "object": [{**doc["object"][0], "angular_velocity": [1, 2]}]}, base_dir=ball_dir
        )

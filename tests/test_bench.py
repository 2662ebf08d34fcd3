"""The benchmark harness itself, in its quick CPU mode (the figures come from the GPU machine)."""

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))

import bench  # noqa: E402
import bench_check  # noqa: E402

import warpfem  # noqa: E402
from warpfem.scene import load_scene  # noqa: E402


@pytest.mark.slow
def test_quick_benchmark_writes_a_complete_json(tmp_path):
    cmd = [
        sys.executable,
        str(ROOT / "scripts" / "bench.py"),
        "--quick",
        "--out",
        str(tmp_path),
        "--cache-dir",
        str(tmp_path / "cache"),
        "--label",
        "check-1",
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    (path,) = tmp_path.glob("bench-quick-check-1-cpu-*.json")
    result = json.loads(path.read_text())
    assert result["label"] == "check-1"
    env = result["environment"]
    assert env["warp"] and env["commit"] and env["device_alias"] == "cpu"
    runs = result["runs"]
    assert [(r["kind"], r["n"]) for r in runs] == [("pile", 1), ("pile", 2), ("mixed", 2)]
    assert runs[1]["tets"] == 2 * runs[0]["tets"] and runs[1]["dense_triangles"] == 2 * runs[0]["dense_triangles"]
    for run in runs:
        assert run["ms_per_frame"] > 0 and run["cg_iterations_per_step"] > 0
        assert {"elastic", "solve", "map", "output"} <= set(run["phase_ms"]) and run["phase_ms"]["output"] > 0
        assert run["lowest_dense_point_m"] > -0.05  # they fell onto the ground and stayed above it
        # the phase split re-ran the timed frames from their start: on the CPU it ends where they ended
        assert run["phase_rerun_gap_m"] == 0.0
    assert "collision" in runs[1]["phase_ms"] and "collision" not in runs[0]["phase_ms"]
    mixed = runs[2]  # a bunny and a ball: its own dense check over the run and at the end, the ground included
    assert mixed["bodies"] == 2 and mixed["dense_check"]["frames_checked"] == 8 and "frame_error" not in mixed
    assert {"relative", "below_relative"} <= set(mixed["dense_check"]["end"]) & set(mixed["dense_check"]["worst"])
    assert all(run["cg_tolerance"] == 1e-4 for run in runs)  # the default scene's
    error = runs[0]["frame_error"]  # one frame against converged CG, from the same state
    assert error["converged_cg_tolerance"] == 1e-6 and 0.0 <= error["rms_m"] <= error["max_m"] < 1e-3
    assert "frame_error" not in runs[1]  # pile 2 is not in --deviation's default list
    deviation = runs[0]["settle_deviation"]  # one bunny against its converged run: close, not identical
    assert deviation["converged_substeps"] == 4 * runs[0]["substeps"]
    assert 0.0 < deviation["rms_m"] <= deviation["max_m"] < 0.05
    cg = result["cg_at_scale"]
    assert cg["cg_iteration_us"] > 0 and cg["stream_bandwidth_GBps"] > 0 and cg["ratio_to_spmv_floor"] > 0
    assert cg["stored_blocks"] < cg["nnz_blocks"] and set(cg["cg_iteration_us_by_chunk"]) == {"1", "2", "4", "8", "64"}
    assert set(cg["cg_iteration_us_by_path"]) == {"grid", "launches"}
    assert cg["cg_iteration_us"] == min(cg["cg_iteration_us_by_path"].values())


@pytest.mark.parametrize(
    "script, args, named",
    [
        ("bench.py", ["--piles", "4,x"], "--piles"),
        ("bench.py", ["--paper-substeps", "0"], "--paper-substeps"),
        ("bench.py", ["--deviation", "-1"], "--deviation"),
        ("bench.py", ["--paper-tolerances", "1e-3,1"], "--paper-tolerances"),
        ("bench.py", ["--skip", "pile"], "--skip"),
        ("bench.py", ["--cg-paths", "grid:0"], "--cg-paths"),
        ("bench.py", ["--cg-paths", "fast"], "--cg-paths"),
        ("bench.py", ["--check-bodies", "-1"], "--check-bodies"),
        ("bench.py", ["--check-every", "-2"], "--check-every"),
        ("bench.py", ["--label", "a/b"], "--label"),
        ("bench_newton.py", ["--piles", "1.5"], "--piles"),
        ("bench_end_to_end.py", ["--queue-mb", "-1"], "--queue-mb"),
        ("bench_end_to_end.py", ["--writers", "two"], "--writers"),
        ("bench_end_to_end.py", ["--frames", "0"], "--frames"),
    ],
)
def test_bad_arguments_are_one_line_errors_and_write_nothing(tmp_path, script, args, named):
    cmd = [sys.executable, str(ROOT / "scripts" / script), "--quick", "--out", str(tmp_path / "out"), *args]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    errors = [line for line in done.stderr.splitlines() if "error:" in line]
    assert len(errors) == 1 and named in errors[0] and "Traceback" not in done.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_frame_error_is_the_cg_error_of_one_frame_and_leaves_the_state(tmp_path):
    scene = load_scene(ROOT / "scenes" / "default.toml")
    bunnies = bench.pile(scene, 2, "builtin:bunny", 300, scale=0.5)
    errors = {}
    for tolerance in (1e-1, 1e-4, bench.CONVERGED_CG):
        settings = dataclasses.replace(bunnies, solver=dataclasses.replace(scene.solver, cg_tolerance=tolerance))
        sim = bench.build(settings, "cpu", tmp_path)
        for _ in range(30):  # landed and touching: CG has work to do
            sim.advance()
        before = sim.states[0].x.numpy().copy()
        errors[tolerance] = bench.frame_error(sim, settings, "cpu", tmp_path)["max_m"]
        np.testing.assert_array_equal(sim.states[0].x.numpy(), before)
    # against itself the converged run differs by nothing: the figure isolates CG from everything else
    assert errors[bench.CONVERGED_CG] == 0.0
    assert 0.0 < errors[1e-4] < 1e-2 * errors[1e-1]


def test_dense_check_every_frame_is_the_worst_of_separate_checks_of_each_frame(tmp_path):
    """A ball thrown down at 20 m/s from 1 m onto another, 8 frames: the bench's check of every frame finds the worst of
    the dense check made on each frame of a separate run of the same scene (CPU: the runs match bit for bit), the
    impact's, whether a frame is checked as it comes (before the timed frames) or copied and checked after them;
    checking every third frame reads frames 3 and 6 and the last, which miss the impact. The worst's frame is
    named, and each checked frame's figure listed."""
    from warpfem.io.penetration import frame_penetration

    scene = load_scene(ROOT / "tests" / "data" / "golden" / "two_balls.toml")
    top = dataclasses.replace(scene.objects[1], translate=(0.05, 1.0, 0.0), velocity=(0.0, -20.0, 0.0))
    scene = dataclasses.replace(scene, objects=[scene.objects[0], top])
    separate = bench.build(scene, "cpu", tmp_path)
    depths, pairs = [], []
    for _ in range(8):
        separate.advance()
        now = frame_penetration(separate, bodies=True)
        depths.append(now.relative)
        pairs.append(now.inside)
    assert max(depths) > 2 * max(depths[2], depths[5], depths[7])  # checks of frames 3 and 6 miss the impact
    for every, timed_from, frames in ((1, 4, range(1, 9)), (1, 1, range(1, 9)), (3, 4, (3, 6, 8))):
        expected = [depths[f - 1] for f in frames]
        sim = bench.build(scene, "cpu", tmp_path)
        check = bench_check.DenseCheck(sim, 8, timed_from, most_bodies=2, every=every)
        for f in range(1, 9):
            sim.advance()
            sim.map_dense()
            check.after(f)
        result = check.result()
        assert result["frames_checked"] == len(expected)
        assert result["worst"]["relative"] == pytest.approx(max(expected), abs=0.0)
        assert result["end"]["relative"] == pytest.approx(depths[7], abs=0.0)
        deepest = max(frames, key=lambda f: depths[f - 1])  # the frame the worst was found at (0: none)
        assert result["worst"]["frame"] == (deepest if depths[deepest - 1] > 0 else 0)
        assert result["frames"] == list(frames) and result["by_frame"]["inside"] == pytest.approx(expected, abs=0.0)
        assert result["by_frame"]["pair"] == [pairs[f - 1] for f in frames] and "top in ball" in pairs
    ends_only = bench_check.DenseCheck(bench.build(scene, "cpu", tmp_path), 8, 4, most_bodies=1, every=1)
    assert ends_only.direct == set() and set(ends_only.buffers) == {8}  # more bodies than checked over the run


def test_newton_dense_meshes_follow_its_tets_as_warpfem_maps_them(tmp_path):
    """The peer's dense check carries each body's dense mesh on the particles Newton moves (the same tet
    meshes, in body order): given warpfem's own tet positions for two turned, placed bunnies, it measures the
    dense points warpfem maps itself (``Simulation.dense_points``)."""
    import bench_newton

    scene = bench.pile(load_scene(ROOT / "scenes" / "default.toml"), 2, "builtin:bunny", 300, scale=0.5)
    sim = bench.build(scene, "cpu", tmp_path)
    for _ in range(3):
        sim.advance()
    check = bench_newton.NewtonDenseCheck(scene.objects, tmp_path, "cpu", 3)
    measured = []
    check.check.measure = lambda points, **_: measured.append(points) or warpfem.Penetration()
    check.after(3, sim.states[0].x)
    (points,) = measured
    for ours, theirs in zip(sim.dense_points(), points, strict=True):
        np.testing.assert_allclose(theirs, ours, atol=1e-5)
    assert check.result()["frames"] == [3]


def test_mixed_pile_spreads_sizes_and_stiffnesses_and_drops_every_body_from_above_the_ground(tmp_path):
    """Each body of the mixed pile, placed as the scene places it (read back with trimesh), has the size asked
    for (its own bounding box's diagonal), its lowest point 0.2 m above the ground and a box apart from the
    others'; the moduli are the log-spaced ones, each once."""
    import trimesh

    from warpfem.build import euler_rotation

    ball = str(ROOT / "tests" / "data" / "golden" / "ball.obj")
    box = str(tmp_path / "box.obj")
    trimesh.creation.box(extents=(2.0, 1.0, 3.0)).export(box)
    scene = load_scene(ROOT / "scenes" / "default.toml")
    mixed = bench.mixed_pile(scene, [(ball, 120), (box, 100)], copies=3, sizes=(0.5, 1.0), youngs=(1e5, 1e7))
    assert [o.mesh for o in mixed.objects] == [ball, box] * 3
    own = [obj.scale * trimesh.load(obj.mesh, force="mesh").vertices for obj in mixed.objects]
    placed = [v @ euler_rotation(o.rotate).T + np.asarray(o.translate) for v, o in zip(own, mixed.objects, strict=True)]
    np.testing.assert_allclose([np.linalg.norm(np.ptp(v, axis=0)) for v in own], np.linspace(0.5, 1.0, 6))
    np.testing.assert_allclose([p[:, 1].min() for p in placed], 0.2, atol=1e-9)
    np.testing.assert_allclose(sorted(o.young for o in mixed.objects), np.geomspace(1e5, 1e7, 6))
    for i, a in enumerate(placed):
        for b in placed[i + 1 :]:
            assert np.any(a.min(axis=0) > b.max(axis=0)) or np.any(b.min(axis=0) > a.max(axis=0))


def test_mixed_pile_with_a_small_side_stacks_its_bodies(tmp_path):
    """With two bodies a row, eight bodies stand in two layers of four, 1.6 m apart, each body above the
    footprint of the one below it (so they land on each other), and no two boxes overlap at the start."""
    import trimesh

    from warpfem.build import euler_rotation

    ball = str(ROOT / "tests" / "data" / "golden" / "ball.obj")
    box = str(tmp_path / "box.obj")
    trimesh.creation.box(extents=(2.0, 1.0, 3.0)).export(box)
    scene = load_scene(ROOT / "scenes" / "default.toml")
    mixed = bench.mixed_pile(scene, [(ball, 120), (box, 100)], copies=4, sizes=(0.5, 1.0), side=2)
    own = [obj.scale * trimesh.load(obj.mesh, force="mesh").vertices for obj in mixed.objects]
    placed = [v @ euler_rotation(o.rotate).T + np.asarray(o.translate) for v, o in zip(own, mixed.objects, strict=True)]
    np.testing.assert_allclose([p[:, 1].min() for p in placed], [0.2] * 4 + [1.8] * 4, atol=1e-9)
    for i, a in enumerate(placed):
        for b in placed[i + 1 :]:
            assert np.any(a.min(axis=0) > b.max(axis=0)) or np.any(b.min(axis=0) > a.max(axis=0))
    for low, high in zip(placed[:4], placed[4:], strict=True):  # the same grid cell, one layer up
        np.testing.assert_allclose(low.mean(axis=0)[[0, 2]], high.mean(axis=0)[[0, 2]], atol=0.6)


@pytest.mark.parametrize(
    "setting, message",
    [
        ("young", "expected section.key=value"),
        ("bogus.x=1", "no attribute 'bogus'"),
        ("collision.bogus=1", "bogus"),
        ("collision.stiffness=-1", "stiffness"),
        ("object.young=nan", "young"),
        ("solver.elements=cubic", "elements"),
        ("collision.offset=[1,", "neither TOML nor a bare word"),
    ],
)
def test_a_bad_set_is_a_one_line_error_before_anything_runs(tmp_path, setting, message):
    """``--set`` with no key, an unknown section or key, or a value the scene refuses stops the run with one
    line naming it, before any scene runs or any file is written."""
    with pytest.raises(SystemExit, match=message) as stop:
        bench.main(["--quick", "--out", str(tmp_path), "--cache-dir", str(tmp_path / "cache"), "--set", setting])
    assert "\n" not in str(stop.value)
    assert not list(tmp_path.iterdir())


def test_set_reads_a_bare_word_as_a_string():
    """``--set solver.elements=quadratic`` needs no TOML quotes; a TOML value keeps its type."""
    scene = load_scene(ROOT / "scenes" / "default.toml")
    assert bench.replaced(scene, "solver.elements=quadratic").solver.elements == "quadratic"
    assert bench.replaced(scene, 'solver.elements="quadratic"').solver.elements == "quadratic"
    assert bench.replaced(scene, "collision.offset=0.003").collision.offset == 0.003


def _floor_beside(path: Path, vertices: int, frames: int):
    """scripts/bench_end_to_end.py's RawBeside around a writer taking ``frames`` frames of ``vertices`` points:
    the floor, the order of the writes ("raw" and "writer", in turn) and the raw file's size."""
    import bench_end_to_end as e2e

    beside = e2e.RawBeside(path)
    order: list[str] = []
    write = beside.write
    beside.write = lambda points: (order.append("raw"), write(points))
    both = beside.after(lambda frame, points, boxes: order.append("writer"))
    points = [np.zeros((vertices, 3), np.float32)]
    for frame in range(frames):
        both(frame, points, None)
    size = path.stat().st_size
    beside.close()
    return beside, order, size


def test_end_to_end_floor_is_written_beside_a_sample_of_large_frames(tmp_path, monkeypatch):
    """scripts/bench_end_to_end.py's raw floor: beside every frame up to its sample size, beside one frame in
    ceil(size / sample size) above, alternately before and after the writer takes the frame, and reported per
    frame it was written beside (the bytes on disk count the frames)."""
    import bench_end_to_end as e2e

    monkeypatch.setattr(e2e, "RAW_SAMPLE_BYTES", 1000)
    for vertices, sampled in [(50, range(8)), (100, (0, 2, 4, 6))]:  # 600 and 1,200 bytes a frame
        beside, order, size = _floor_beside(tmp_path / f"{vertices}.raw", vertices, 8)
        assert beside.samples == len(sampled) and size == len(sampled) * 12 * vertices
        writers = [k for k, what in enumerate(order) if what == "writer"]
        raws = [k for k, what in enumerate(order) if what == "raw"]
        for n, frame in enumerate(sampled):  # before the writer's frame on every other sample, after it on the rest
            assert raws[n] == (writers[frame] - 1 if n % 2 == 0 else writers[frame] + 1)
        assert beside.per_frame_ms()[0] == pytest.approx(1e3 * beside.seconds / len(sampled))


@pytest.mark.parametrize(
    "args, named",
    [([], "expected COMMIT STEP"), (["abc123"], "expected COMMIT STEP"), (["abc123", "p256 --piles 256"], "p256")],
)
def test_device_bench_refuses_a_bad_step_in_one_line_before_running(tmp_path, args, named):
    """The GPU machine's runner (``scripts/device_bench.sh``) stops on a missing or malformed step with one line
    and exit code 2, before it links, copies or runs anything."""
    script = ROOT / "scripts" / "device_bench.sh"
    done = subprocess.run(["bash", str(script), *args], cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and done.stdout == ""
    assert len(done.stderr.splitlines()) == 1 and named in done.stderr
    assert not list(tmp_path.iterdir())

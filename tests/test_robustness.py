"""Nothing lost: runs stopped by signals, NaN or exceptions keep their frames; --overwrite; memory; pickle."""

import os
import pickle
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh
from pxr import Usd, UsdGeom

import warpfem.memory as memory
from warpfem.build import add_body, add_prepared_body, placed_geometry, scene_samples, solver_of
from warpfem.cli import main
from warpfem.errors import SimulationError
from warpfem.io.usd import UsdWriter
from warpfem.prep.pipeline import prepare
from warpfem.scene import load_scene
from warpfem.sim.model import ModelBuilder
from warpfem.simulation import Simulation

SCENE = """
[scene]
frames = {frames}
substeps = 1
[solver]
cg_mode = "fixed"
cg_iterations = 10
[collision]
enabled = {collision}
[[object]]
name = "ball"
mesh = "ball.obj"
faces = 100
scale = 0.3
translate = [0.0, 0.5, 0.0]
young = 1e5
"""


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """A 320-triangle ball, scenes of 6 and a million frames, and a filled preprocessing cache."""
    path = tmp_path_factory.mktemp("robust")
    trimesh.creation.icosphere(subdivisions=2).export(path / "ball.obj")
    (path / "short.toml").write_text(SCENE.format(frames=6, collision="false"))
    (path / "endless.toml").write_text(SCENE.format(frames=1_000_000, collision="false"))
    second = SCENE[SCENE.index("[[object]]") :].replace('"ball"', '"ball2"').replace("0.5, 0.0]", "1.2, 0.0]")
    (path / "touching.toml").write_text(SCENE.format(frames=6, collision="true") + second)
    prepare(path / "ball.obj", faces=100, cache_dir=path / "cache")
    return path


def _run(folder, *args):
    args = ["run", folder / "short.toml", "--device", "cpu", "--cache-dir", folder / "cache", *args]
    return main([str(a) for a in args])


def _warpfem_lines(err):
    """stderr lines from warpfem itself (a machine without a GPU adds Warp's CUDA warning)."""
    return [line for line in err.strip().splitlines() if not line.startswith("Warp CUDA warning")]


def _frames(path):
    """Time samples of /World/ball.points, checked to be 0..end with endTimeCode == end; the points."""
    stage = Usd.Stage.Open(str(path))
    attr = UsdGeom.Mesh(stage.GetPrimAtPath("/World/ball")).GetPointsAttr()
    times = attr.GetTimeSamples()
    assert times == [float(t) for t in range(len(times))]
    assert stage.GetEndTimeCode() == times[-1]
    assert UsdGeom.Mesh(stage.GetPrimAtPath("/World/ball")).GetExtentAttr().GetTimeSamples() == times
    return [np.array(attr.Get(t)) for t in times]


def _leftovers(folder):
    return [p.name for p in folder.iterdir() if ".tmp-" in p.name]


@pytest.fixture(scope="module")
def reference(folder):
    """The first 301 frames of an uninterrupted run (the CPU run is deterministic)."""
    out = folder / "reference.usdc"
    assert _run(folder, "--out", out, "--frames", "300", "--quiet") == 0
    return _frames(out)


def _child(folder, out, save_every="0"):
    cmd = [sys.executable, "-m", "warpfem", "run", str(folder / "endless.toml"), "--out", str(out)]
    cmd += ["--device", "cpu", "--cache-dir", str(folder / "cache"), "--save-every", save_every, "--quiet"]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _saved_frames(path):
    """Frames readable through the file at ``path`` now (its clips, if any; it may be replaced while we read:
    the old inode stays, and chunks are never rewritten)."""
    stage = Usd.Stage.Open(str(path))
    return UsdGeom.Mesh(stage.GetPrimAtPath("/World/ball")).GetPointsAttr().GetNumTimeSamples()


@pytest.mark.parametrize(
    "sig, wait, code",
    [
        (signal.SIGKILL, 0.0, -9),  # just after the first snapshot
        (signal.SIGKILL, 0.7, -9),
        (signal.SIGTERM, 0.3, 143),
        (signal.SIGINT, 0.3, 130),
    ],
)
def test_stopped_child_leaves_a_valid_file_with_the_frames_done(folder, reference, tmp_path, sig, wait, code):
    out = tmp_path / "anim.usdc"
    child = _child(folder, out)
    deadline = time.monotonic() + 60
    while not out.exists() and child.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert out.exists(), child.communicate()
    time.sleep(wait)
    seen = _saved_frames(out)
    child.send_signal(sig)
    _, err = child.communicate(timeout=60)
    assert child.returncode == code, err
    frames = _frames(out)
    assert len(frames) >= seen >= 1
    for got, want in zip(frames, reference, strict=False):
        np.testing.assert_array_equal(got, want)
    if sig != signal.SIGKILL:  # every finished frame saved, temp file gone, one line naming the file
        assert _leftovers(tmp_path) == []
        lines = _warpfem_lines(err)
        assert len(lines) == 1 and str(out) in lines[0], err
        assert lines[0].startswith("warpfem: terminated" if sig == signal.SIGTERM else "warpfem: interrupted")


def test_sigterm_before_the_first_frame_writes_nothing(folder, tmp_path):
    out = tmp_path / "anim.usdc"
    child = _child(folder, out, save_every="1000")
    time.sleep(0.5)  # still importing or preparing
    child.send_signal(signal.SIGTERM)
    child.communicate(timeout=60)
    assert child.returncode in (143, -signal.SIGTERM)
    assert list(tmp_path.iterdir()) == []


def test_chunks_follow_save_every_and_are_never_rewritten(tmp_path):
    faces = np.array([[0, 1, 2]])
    writer = UsdWriter(tmp_path / "a.usdc", [("tri", faces)], fps=30.0, save_every=0.0)
    seen = {}
    for f in range(5):
        writer.add_frame(f, [np.eye(3) * (f + 1)])
        assert writer.chunks == f + 1
        stage = Usd.Stage.Open(str(tmp_path / "a.usdc"))
        assert stage.GetEndTimeCode() == f
        attr = UsdGeom.Mesh(stage.GetPrimAtPath("/World/tri")).GetPointsAttr()
        np.testing.assert_array_equal(np.array(attr.Get(f)), np.eye(3) * (f + 1))
        del stage, attr  # let the next open read the replaced file, not the layer still registered
        chunks = sorted((tmp_path / "a.clips").glob("a.*.usdc"))
        assert len(chunks) == f + 1
        for chunk in chunks:  # a chunk once written keeps its inode and bytes
            st = chunk.stat()
            assert seen.setdefault(chunk.name, (st.st_ino, st.st_mtime_ns)) == (st.st_ino, st.st_mtime_ns)
    writer.close()
    assert _leftovers(tmp_path) == [] and _leftovers(tmp_path / "a.clips") == []
    lazy = UsdWriter(tmp_path / "b.usdc", [("tri", faces)], fps=30.0, save_every=3600.0)
    lazy.add_frame(0, [np.eye(3)])
    assert lazy.chunks == 0 and not (tmp_path / "b.usdc").exists()
    lazy.close()
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith("b")) == ["b.usdc"]


def test_writer_without_overwrite_refuses_an_existing_file(tmp_path):
    path = tmp_path / "a.usdc"
    path.write_bytes(b"precious")
    with pytest.raises(FileExistsError, match="exists"):
        UsdWriter(path, [("tri", np.array([[0, 1, 2]]))], fps=30.0, overwrite=False)
    writer = UsdWriter(tmp_path / "b.usdc", [("tri", np.array([[0, 1, 2]]))], fps=30.0, overwrite=False)
    writer.add_frame(0, [np.eye(3)])
    (tmp_path / "b.usdc").write_bytes(b"appeared meanwhile")
    with pytest.raises(FileExistsError):
        writer.close()
    assert path.read_bytes() == b"precious" and (tmp_path / "b.usdc").read_bytes() == b"appeared meanwhile"
    assert _leftovers(tmp_path) == []


@pytest.mark.parametrize("stop", ["nan", "exception"])
def test_nan_or_kernel_exception_keeps_the_frames_before(folder, tmp_path, monkeypatch, capsys, stop):
    import warpfem.simulation as simulate

    original = simulate.Simulation.check_finite

    def check_finite(self):
        if self.frame == 4:
            if stop == "nan":
                raise SimulationError(f"frame {self.frame}: body 'ball' became NaN/Inf")
            raise RuntimeError("a kernel failed")
        original(self)

    monkeypatch.setattr(simulate.Simulation, "check_finite", check_finite)
    out = tmp_path / "anim.usdc"
    if stop == "nan":
        assert _run(folder, "--out", out, "--quiet") == 1
        assert "frames before it were written" in capsys.readouterr().err
    else:
        with pytest.raises(RuntimeError, match="kernel"):
            _run(folder, "--out", out, "--quiet")
    assert len(_frames(out)) == 4  # frames 0..3
    assert _leftovers(tmp_path) == []


def test_out_is_not_overwritten_without_overwrite(folder, tmp_path, capsys):
    out = tmp_path / "anim.usdc"
    out.write_bytes(b"precious")
    assert _run(folder, "--out", out) == 2
    lines = _warpfem_lines(capsys.readouterr().err)
    assert len(lines) == 1 and "--overwrite" in lines[0] and str(out) in lines[0]
    assert out.read_bytes() == b"precious"
    assert _run(folder, "--out", out, "--overwrite", "--quiet") == 0
    assert len(_frames(out)) == 7
    capsys.readouterr()
    (tmp_path / "anim.mp4").write_bytes(b"precious")
    assert main(["render", str(out), "--out", str(tmp_path / "anim.mp4"), "--device", "cpu"]) == 2  # render too
    assert "--overwrite" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["anim.mp4", "anim.usdc"]
    assert (tmp_path / "anim.mp4").read_bytes() == b"precious"


def test_not_enough_memory_is_one_line_with_both_numbers_and_writes_nothing(folder, tmp_path, monkeypatch, capsys):
    import warpfem.simulation as simulate

    monkeypatch.setattr(memory, "free_bytes", lambda device: (500, 2000))
    monkeypatch.setattr(simulate.ModelBuilder, "finalize", lambda *a: pytest.fail("allocated after the refusal"))
    out = tmp_path / "anim.usdc"
    assert _run(folder, "--out", out) == 2
    lines = _warpfem_lines(capsys.readouterr().err)
    scene = load_scene(folder / "short.toml")
    body = prepare(folder / "ball.obj", faces=100, cache_dir=folder / "cache")
    samples = scene_samples(scene, [body])[0]
    need = memory.scene_estimate(scene, [body], [placed_geometry(scene.objects[0], body, samples)[1]])
    assert len(lines) == 1, lines
    assert f"needs about {memory.format_bytes(need.total)}" in lines[0] and "only 500 B of 2.0 kB" in lines[0]
    assert list(tmp_path.iterdir()) == []


def _device_bytes(*roots):
    """Bytes of every distinct wp.array reachable from ``roots`` (attributes, lists, two levels deep)."""
    import warp as wp

    seen, total = set(), 0
    stack = [(r, 0) for r in roots]
    while stack:
        obj, depth = stack.pop()
        if isinstance(obj, wp.array):
            if obj.ptr not in seen and obj.ptr is not None:
                seen.add(obj.ptr)
                total += obj.capacity
        elif isinstance(obj, (list, tuple)):
            stack += [(o, depth) for o in obj]
        elif depth < 3 and type(obj).__module__.startswith("warpfem") and hasattr(obj, "__dict__"):
            stack += [(v, depth + 1) for v in vars(obj).values()]
    return total


@pytest.mark.parametrize("scene_name", ["short.toml", "touching.toml"])
def test_memory_estimate_matches_the_arrays_allocated(folder, scene_name):
    scene = load_scene(folder / scene_name)
    body = prepare(folder / "ball.obj", faces=100, cache_dir=folder / "cache")
    samples = scene_samples(scene, [body] * len(scene.objects))
    placed = [placed_geometry(*where) for where in zip(scene.objects, [body] * len(samples), samples, strict=True)]
    builder = ModelBuilder()
    for obj, where in zip(scene.objects, placed, strict=True):
        add_prepared_body(builder, obj, body, where)
    model = builder.finalize("cpu")
    solver = solver_of(scene, model)
    sim = Simulation.from_model(model, solver, scene.substeps, scene.fps)
    real = _device_bytes(model, solver, sim)  # the tet trees are wp.arrays (the body BVH's few nodes are not)
    assert (solver.collider is not None) == (len(scene.objects) == 2)
    need = memory.scene_estimate(scene, [body] * len(scene.objects), [g for _, g in placed]).total
    assert 0.75 < need / real < 1.5, (need, real)
    free, total = memory.free_bytes("cpu")
    assert 0 < free <= total


class _Trap:
    """Unpickling this touches a marker file: proof that code from the file ran."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return Path.touch, (self.marker,)


def test_pickled_cache_file_is_refused_and_never_run(folder, tmp_path):
    cache = tmp_path / "cache"
    cache.mkdir()
    (entry,) = (p for p in (folder / "cache").glob("*.npz") if not p.name.startswith("samples-"))  # the body's
    with np.load(entry, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    marker = tmp_path / "code-ran"
    arrays["embed_tet"] = np.array([_Trap(marker)], dtype=object)
    np.savez(cache / entry.name, **arrays)
    with np.load(cache / entry.name, allow_pickle=True) as data:  # the payload is live where pickle is allowed
        pickle.loads(pickle.dumps(data["embed_tet"]))
    assert marker.exists()
    marker.unlink()

    body = prepare(folder / "ball.obj", faces=100, cache_dir=cache)
    assert body.stats["cache"] == "miss" and not marker.exists()
    with np.load(cache / entry.name, allow_pickle=False) as data:  # rebuilt as plain arrays
        assert data["embed_tet"].dtype == np.int32


def _rss_bytes():
    with open("/proc/self/statm") as stream:
        return int(stream.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


@pytest.mark.slow
def test_ten_thousand_frames_keep_memory_flat_and_the_file_valid(tmp_path):
    cube = trimesh.creation.box()
    tets = np.array([[0, 1, 3, 5], [0, 3, 2, 6], [0, 5, 4, 6], [3, 5, 6, 7], [0, 3, 5, 6]])
    x = np.asarray(cube.vertices) + [0.0, 1.0, 0.0]
    tets = np.array([t if np.linalg.det(x[t[1:]] - x[t[0]]) > 0 else t[[0, 2, 1, 3]] for t in tets])
    home = np.array([np.flatnonzero((tets == i).any(axis=1))[0] for i in range(8)])  # a tet holding each corner
    scene = load_scene_text(tmp_path, 10_000)
    builder = ModelBuilder()
    add_body(
        builder,
        "cube",
        x,
        tets,
        young=1e5,
        poisson=0.3,
        density=1000.0,
        dense_faces=cube.faces,
        embed_tet=home,
        embed_bary=(tets[home] == np.arange(8)[:, None]).astype(float),
    )
    model = builder.finalize("cpu")
    sim = Simulation.from_model(model, solver_of(scene, model), 1, 60.0)
    rss = {}
    for frame in range(1, 5_001):  # the simulation alone: flat once warm
        sim.advance()
        sim.dense_points()
        if frame in (2_000, 5_000):
            rss[frame] = _rss_bytes()
    assert (rss[5_000] - rss[2_000]) / 3_000 < 256, rss  # allocator noise only; a leaked state would be more
    out = tmp_path / "long.usdc"
    with UsdWriter(out, [("cube", cube.faces)], fps=60.0, save_every=2.0) as writer:
        writer.add_frame(0, sim.dense_points())
        for frame in range(1, 10_001):
            sim.advance()
            if frame % 100 == 0:
                sim.check_finite()
            writer.add_frame(frame, sim.dense_points())
            if frame in (2_000, 10_000):
                rss[-frame] = _rss_bytes()
    # with the writer, memory grows by the samples the layer keeps until the end: 120 B of points and extent
    # per frame plus USD's bookkeeping (about 400-1000 B measured), nothing near the simulation's arrays
    assert (rss[-10_000] - rss[-2_000]) / 8_000 < 2048, rss
    stage = Usd.Stage.Open(str(out))
    attr = UsdGeom.Mesh(stage.GetPrimAtPath("/World/cube")).GetPointsAttr()
    assert attr.GetNumTimeSamples() == 10_001 and stage.GetEndTimeCode() == 10_000
    assert np.isfinite(np.array(attr.Get(10_000))).all()


def load_scene_text(folder, frames):
    """A scene (gravity, ground, no collisions) for a body built by hand; its mesh file is never read."""
    path = folder / "hand.toml"
    path.write_text(SCENE.format(frames=frames, collision="false").replace('"ball.obj"', '"builtin:bunny"'))
    return load_scene(path)

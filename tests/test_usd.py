"""UsdWriter: read back with usd-core, validate, atomic close, abort and interrupts."""

from __future__ import annotations

import contextlib
import os

import numpy as np
import pytest

from warpfem.io.usd import Prop, UsdWriter


def bodies_and_frames(n_frames: int = 5, seed: int = 0):
    """Three small bodies (tetrahedron surface, quad as two triangles, octahedron) and their motion."""
    rng = np.random.default_rng(seed)
    tet = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    quad = np.array([[0, 1, 2], [0, 2, 3]])
    octa = np.array(
        [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]],
        dtype=np.int32,
    )
    bodies = [("tet", tet), ("quad_1", quad), ("octa", octa)]
    counts = [4, 4, 6]
    frames = [[rng.normal(size=(n, 3)) * (1 + f) for n in counts] for f in range(n_frames)]
    return bodies, frames


def validation_errors(stage):
    from pxr import UsdValidation

    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    assert len(validators) > 0
    ctx = UsdValidation.ValidationContext(validators)
    return [e.GetMessage() for e in ctx.Validate(stage) if e.GetType() == UsdValidation.ValidationErrorType.Error]


@pytest.mark.parametrize("workers", [0, 3], ids=["inline", "3 writer processes"])
@pytest.mark.parametrize("chunk_bytes", [1 << 20, 100, 400], ids=["one file", "a clip per frame", "clips"])
@pytest.mark.parametrize("given", [False, True], ids=["extents read off the points", "extents given"])
@pytest.mark.parametrize("ext", [".usdc", ".usda"])
def test_round_trip(tmp_path, ext, chunk_bytes, workers, given):
    from pxr import Sdf, Usd, UsdGeom

    bodies, frames = bodies_and_frames(5)
    path = tmp_path / f"out{ext}"
    writer = UsdWriter(path, bodies, fps=30.0, up_axis="Z", chunk_bytes=chunk_bytes, workers=workers)
    for f, points in enumerate(frames):
        boxes = [[np.float32(p).min(axis=0), np.float32(p).max(axis=0)] for p in points] if given else None
        writer.add_frame(f, points, extents=boxes)
    assert writer.frames_added == 5
    assert writer.close() == path
    assert [p.name for p in tmp_path.rglob("*") if ".tmp-" in p.name] == []  # staged topology moved or dropped
    frame_bytes = 12 * 14
    clips = sorted(p.name for p in (tmp_path / "out.clips").glob("out.*.usdc"))
    assert len(clips) == (0 if chunk_bytes > 5 * frame_bytes else -(-5 // -(-chunk_bytes // frame_bytes)))

    expected_format = "usda" if ext == ".usda" else "usdc"
    assert Sdf.Layer.FindOrOpen(str(path)).GetFileFormat().formatId == expected_format
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == "Z"
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetTimeCodesPerSecond() == 30.0
    assert stage.GetFramesPerSecond() == 30.0
    assert stage.GetStartTimeCode() == 0.0
    assert stage.GetEndTimeCode() == 4.0
    assert stage.GetDefaultPrim().GetPath() == Sdf.Path("/World")
    assert stage.GetDefaultPrim().GetTypeName() == "Xform"
    assert [p.GetName() for p in stage.GetPseudoRoot().GetChildren()] == ["World"]
    assert [p.GetName() for p in stage.GetDefaultPrim().GetChildren()] == ["tet", "quad_1", "octa"]

    for i, (name, faces) in enumerate(bodies):
        prim = stage.GetPrimAtPath(f"/World/{name}")
        assert prim.GetTypeName() == "Mesh"
        mesh = UsdGeom.Mesh(prim)
        assert list(mesh.GetFaceVertexCountsAttr().Get()) == [3] * len(faces)
        assert list(mesh.GetFaceVertexIndicesAttr().Get()) == faces.ravel().tolist()
        assert mesh.GetFaceVertexIndicesAttr().GetNumTimeSamples() == 0
        assert mesh.GetSubdivisionSchemeAttr().Get() == "none"
        assert mesh.GetSubdivisionSchemeAttr().HasAuthoredValue()
        assert mesh.GetOrientationAttr().Get() == "rightHanded"
        assert not mesh.GetNormalsAttr().HasAuthoredValue()
        points_attr, extent_attr = mesh.GetPointsAttr(), mesh.GetExtentAttr()
        assert points_attr.GetTimeSamples() == [float(f) for f in range(5)]
        assert extent_attr.GetTimeSamples() == [float(f) for f in range(5)]
        for f, points in enumerate(frames):
            got = np.array(points_attr.Get(f), dtype=np.float64)
            np.testing.assert_allclose(got, points[i], rtol=1e-6, atol=1e-6)
            ext_got = np.array(extent_attr.Get(f))
            expected = points[i].astype(np.float32)
            np.testing.assert_array_equal(ext_got[0], expected.min(axis=0))
            np.testing.assert_array_equal(ext_got[1], expected.max(axis=0))
            # usd-core's own extent computation agrees.
            computed = UsdGeom.Boundable.ComputeExtentFromPlugins(mesh, Usd.TimeCode(f))
            np.testing.assert_allclose(np.array(computed), ext_got, rtol=1e-6)

    assert validation_errors(stage) == []


def test_temp_file_gone_and_no_partial_target(tmp_path):
    bodies, frames = bodies_and_frames(2)
    path = tmp_path / "anim.usdc"
    writer = UsdWriter(path, bodies, fps=60.0)
    writer.add_frame(0, frames[0])
    writer.add_frame(1, frames[1])
    # before close only hidden temporaries: the samples' stream and the clips' staged topology; no partial target
    hidden = sorted(p.name for p in tmp_path.iterdir())
    pid = os.getpid()
    assert not path.exists() and hidden == [f".anim.clips.tmp-{pid}", f".warpfem-chunk-0.tmp-{pid}.usdc"]
    writer.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["anim.usdc"]


def test_close_replaces_existing_file(tmp_path):
    from pxr import Usd

    bodies, frames = bodies_and_frames(3)
    path = tmp_path / "anim.usdc"
    path.write_bytes(b"old content")
    with UsdWriter(path, bodies, fps=24.0) as writer:
        for f, points in enumerate(frames):
            writer.add_frame(f, points)
        assert path.read_bytes() == b"old content"
    stage = Usd.Stage.Open(str(path))
    assert stage.GetEndTimeCode() == 2.0 and stage.GetTimeCodesPerSecond() == 24.0


def test_given_extents_are_checked(tmp_path):
    """Extents the caller gives stand for its points: a non-finite corner is a non-finite frame, named by body."""
    bodies, frames = bodies_and_frames(1)
    writer = UsdWriter(tmp_path / "a.usdc", bodies, fps=60.0)
    boxes = np.array([[p.min(axis=0), p.max(axis=0)] for p in frames[0]], np.float32)
    with pytest.raises(ValueError, match=r"extents must be a \(3, 2, 3\) array, got shape \(2, 2, 3\)"):
        writer.add_frame(0, frames[0], extents=boxes[:2])
    boxes[1, 0, 2] = -np.inf
    with pytest.raises(ValueError, match="body 'quad_1': frame 0 has non-finite points"):
        writer.add_frame(0, frames[0], extents=boxes)
    writer.abort()
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("workers", [0, 2], ids=["inline", "2 writer processes"])
def test_abort_leaves_nothing(tmp_path, workers):
    """Nor the clips' topology staged ahead, inline or by a writer process."""
    bodies, frames = bodies_and_frames(2)
    writer = UsdWriter(tmp_path / "a.usdc", bodies, fps=60.0, workers=workers)
    writer.add_frame(0, frames[0])
    writer.abort()
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(RuntimeError, match="closed"):
        writer.add_frame(1, frames[1])


def test_abort_removes_a_leftover_temp_file(tmp_path):
    bodies, _ = bodies_and_frames(1)
    writer = UsdWriter(tmp_path / "a.usdc", bodies, fps=60.0)
    tmp = tmp_path / f".a.tmp-{os.getpid()}.usdc"
    tmp.write_bytes(b"partial")  # as if an export had died half way
    writer.abort()
    assert list(tmp_path.iterdir()) == []


def test_keyboard_interrupt_keeps_frames_so_far(tmp_path):
    from pxr import Usd, UsdGeom

    bodies, frames = bodies_and_frames(5)
    path = tmp_path / "interrupted.usdc"
    with pytest.raises(KeyboardInterrupt):
        with UsdWriter(path, bodies, fps=60.0) as writer:
            for f, points in enumerate(frames):
                if f == 3:
                    raise KeyboardInterrupt
                writer.add_frame(f, points)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["interrupted.usdc"]
    stage = Usd.Stage.Open(str(path))
    assert stage.GetEndTimeCode() == 2.0
    points = UsdGeom.Mesh(stage.GetPrimAtPath("/World/octa")).GetPointsAttr()
    assert points.GetTimeSamples() == [0.0, 1.0, 2.0]
    np.testing.assert_allclose(np.array(points.Get(2)), frames[2][2], rtol=1e-6, atol=1e-6)
    assert validation_errors(stage) == []


def test_other_exception_after_frames_closes(tmp_path):
    from pxr import Usd

    bodies, frames = bodies_and_frames(2)
    path = tmp_path / "x.usda"
    with pytest.raises(ZeroDivisionError):
        with UsdWriter(path, bodies, fps=60.0) as writer:
            writer.add_frame(0, frames[0])
            _ = 1 / 0
    assert Usd.Stage.Open(str(path)).GetEndTimeCode() == 0.0


def test_an_interrupt_while_another_thread_closes_waits_for_that_close(tmp_path, monkeypatch):
    """A run's writer thread closes the file as the last frame comes; a Ctrl-C reaching the caller meanwhile
    leaves the writer's context with that close still going: it waits for it rather than closing a second
    time, and the file holds every frame."""
    import threading
    import time

    from pxr import Usd

    bodies, frames = bodies_and_frames(3)
    path = tmp_path / "x.usdc"
    writer = UsdWriter(path, bodies, fps=60.0, workers=0)
    slow, calls = writer._write_single, []

    def write_single():
        calls.append(1)
        time.sleep(0.3)
        slow()

    monkeypatch.setattr(writer, "_write_single", write_single)
    with pytest.raises(KeyboardInterrupt):
        with writer:
            for f, points in enumerate(frames):
                writer.add_frame(f, points)
            closing = threading.Thread(target=writer.close)
            closing.start()
            time.sleep(0.05)
            raise KeyboardInterrupt
    closing.join()
    assert calls == [1]
    assert Usd.Stage.Open(str(path)).GetEndTimeCode() == float(len(frames) - 1)


@pytest.mark.parametrize("error", [ZeroDivisionError, KeyboardInterrupt])
def test_exception_before_any_frame_aborts(tmp_path, error):
    bodies, _ = bodies_and_frames(1)
    with pytest.raises(error):
        with UsdWriter(tmp_path / "x.usdc", bodies, fps=60.0):
            raise error
    assert list(tmp_path.iterdir()) == []


def test_close_without_frames_raises_and_writes_nothing(tmp_path):
    bodies, _ = bodies_and_frames(1)
    writer = UsdWriter(tmp_path / "x.usdc", bodies, fps=60.0)
    with pytest.raises(RuntimeError, match="no frame"):
        writer.close()
    assert list(tmp_path.iterdir()) == []


def test_frames_need_not_be_contiguous(tmp_path):
    from pxr import Usd, UsdGeom

    bodies, frames = bodies_and_frames(3)
    path = tmp_path / "sparse.usdc"
    with UsdWriter(path, bodies, fps=60.0) as writer:
        for f, points in zip((0, 2, 10), frames, strict=True):
            writer.add_frame(f, points)
    stage = Usd.Stage.Open(str(path))
    assert stage.GetEndTimeCode() == 10.0
    attr = UsdGeom.Mesh(stage.GetPrimAtPath("/World/tet")).GetPointsAttr()
    assert attr.GetTimeSamples() == [0.0, 2.0, 10.0]


def test_shape_checks(tmp_path):
    bodies, frames = bodies_and_frames(2)
    writer = UsdWriter(tmp_path / "x.usdc", bodies, fps=60.0)
    with pytest.raises(ValueError, match="expected points for 3 bodies, got 2"):
        writer.add_frame(0, frames[0][:2])
    with pytest.raises(ValueError, match=r"'tet': points must be an \(n, 3\) array"):
        writer.add_frame(0, [frames[0][0][:, :2], *frames[0][1:]])
    with pytest.raises(ValueError, match="'octa': 5 points, but its faces use 6 vertices"):
        writer.add_frame(0, [*frames[0][:2], frames[0][2][:5]])
    with pytest.raises(ValueError, match="non-finite"):
        writer.add_frame(0, [np.full((4, 3), np.nan), *frames[0][1:]])
    with pytest.raises(ValueError, match="frame must be an integer >= 0"):
        writer.add_frame(-1, frames[0])
    writer.add_frame(0, frames[0])
    with pytest.raises(ValueError, match="frames must increase"):
        writer.add_frame(0, frames[1])
    # The vertex count is fixed by the first frame.
    with pytest.raises(ValueError, match="'quad_1': 5 points, expected 4"):
        writer.add_frame(1, [frames[1][0], np.zeros((5, 3)), frames[1][2]])
    writer.abort()


@pytest.mark.parametrize(
    ("name", "kwargs", "match"),
    [
        ("x.obj", {}, "must end in .usdc"),
        ("x.usdc", {"bodies": [("1bad", np.array([[0, 1, 2]]))]}, "not a valid USD prim name"),
        ("x.usdc", {"bodies": [("a", np.array([[0, 1, 2]])), ("a", np.array([[0, 1, 2]]))]}, "used twice"),
        ("x.usdc", {"bodies": [("a", np.array([[0, 1, 2, 3]]))]}, r"\(m, 3\) integer array"),
        ("x.usdc", {"bodies": [("a", np.array([[0.0, 1.0, 2.0]]))]}, "integer array"),
        ("x.usdc", {"bodies": [("a", np.array([[0, -1, 2]]))]}, "face indices"),
        ("x.usdc", {"bodies": []}, "at least one body"),
        ("x.usdc", {"fps": 0.0}, "fps"),
        ("x.usdc", {"up_axis": "X"}, "up_axis"),
        ("x.usdc", {"chunk_bytes": 0}, "chunk_bytes"),
        ("x.usdc", {"props": [Prop("obstacles/1ramp", np.eye(3), np.array([[0, 1, 2]]))]}, "prim path"),
        ("x.usdc", {"props": [Prop("obstacles/r", np.full((3, 3), np.nan), np.array([[0, 1, 2]]))]}, "finite"),
        ("x.usdc", {"props": [Prop("obstacles/r", np.eye(3), np.array([[0, 1, 3]]))]}, "vertex indices"),
        ("x.usdc", {"props": [Prop("a/r", np.eye(3), np.array([[0, 1, 2]]))]}, "a body is named 'a'"),
    ],
)
def test_constructor_checks(tmp_path, name, kwargs, match):
    args = {"bodies": [("a", np.array([[0, 1, 2]]))], "fps": 60.0, **kwargs}
    with pytest.raises(ValueError, match=match):
        UsdWriter(tmp_path / name, **args)


def test_missing_output_folder(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        UsdWriter(tmp_path / "no" / "x.usdc", [("a", np.array([[0, 1, 2]]))], fps=60.0)


def _rss_bytes(pid: int | str = "self") -> int:
    with open(f"/proc/{pid}/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _children(pid: int | str = "self") -> list[int]:
    """The process ids of ``pid``'s children (from /proc, whichever thread started them)."""
    from pathlib import Path

    return [int(c) for task in Path(f"/proc/{pid}/task").iterdir() for c in (task / "children").read_text().split()]


def _alive(pid: int) -> bool:
    """Whether process ``pid`` runs (exists and is not a zombie waiting to be reaped)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def _family_rss_bytes() -> int:
    """Resident memory of this process and its children (the writer processes)."""
    return _rss_bytes() + sum(_rss_bytes(child) for child in _children())


@pytest.mark.skipif(not os.path.exists("/proc/self/statm"), reason="needs /proc to read the resident memory")
def test_memory_stays_flat_over_a_long_run_and_every_frame_reads_back(tmp_path):
    """300 frames of 50k vertices (180 MB of samples) in 8 MB chunks through two writer processes: resident
    memory of this process and the writers grows by less than two chunks between frame 100 and the end, and
    the file reads back every frame."""
    from pxr import Usd, UsdGeom

    n, chunk = 50_000, 8 << 20
    rng = np.random.default_rng(1)
    base = rng.normal(size=(n, 3)).astype(np.float32)
    faces = rng.integers(0, n, size=(n, 3))
    path = tmp_path / "long.usdc"
    with UsdWriter(path, [("m", faces)], fps=60.0, save_every=None, chunk_bytes=chunk, workers=2) as writer:
        for f in range(300):
            writer.add_frame(f, [base + np.float32(f)])
            if f == 100:
                assert len(_children()) == 2
                before = _family_rss_bytes()
        grown = _family_rss_bytes() - before
    assert grown < 2 * chunk, f"resident memory grew {grown / 2**20:.1f} MB over 200 frames of 0.6 MB"
    assert writer.chunks == -(-300 // -(-chunk // (12 * n)))
    stage = Usd.Stage.Open(str(path))
    attr = UsdGeom.Mesh(stage.GetPrimAtPath("/World/m")).GetPointsAttr()
    assert attr.GetTimeSamples() == [float(f) for f in range(300)] and stage.GetEndTimeCode() == 299
    for f in (0, 1, 13, 14, 150, 299):
        np.testing.assert_array_equal(np.array(attr.Get(f)), base + np.float32(f))


_KILLED_WRITER = """
import sys
import numpy as np
from warpfem.io.usd import UsdWriter
n = 1000
base = np.random.default_rng(2).normal(size=(n, 3)).astype(np.float32)
faces = np.arange(3 * n).reshape(n, 3) % n
with UsdWriter(sys.argv[1], [("m", faces)], fps=60.0, save_every=None, chunk_bytes=3 * 12 * n, workers=2) as writer:
    for f in range(10**9):
        writer.add_frame(f, [base * np.float32(1 + f)])
"""


def test_a_killed_writer_leaves_every_finished_chunk_readable(tmp_path):
    import signal
    import subprocess
    import sys
    import time

    from pxr import Usd, UsdGeom

    path = tmp_path / "killed.usdc"
    child = subprocess.Popen([sys.executable, "-c", _KILLED_WRITER, str(path)], stderr=subprocess.PIPE)
    deadline = time.monotonic() + 60
    # six chunks on disk: the top-level file lists at least five (it is replaced after each chunk is in place)
    while len(list((tmp_path / "killed.clips").glob("killed.*.usdc"))) < 6 and time.monotonic() < deadline:
        assert child.poll() is None, child.stderr.read()
        time.sleep(0.005)
    writers = _children(child.pid)
    assert writers, "no writer process"
    child.send_signal(signal.SIGKILL)
    child.wait(timeout=60)
    while any(map(_alive, writers)) and time.monotonic() < deadline:
        time.sleep(0.01)  # the writer processes see their socket close and exit
    assert not any(map(_alive, writers)), "a writer process outlived its caller"
    base = np.random.default_rng(2).normal(size=(1000, 3)).astype(np.float32)
    stage = Usd.Stage.Open(str(path))
    attr = UsdGeom.Mesh(stage.GetPrimAtPath("/World/m")).GetPointsAttr()
    times = attr.GetTimeSamples()
    assert len(times) >= 15 and len(times) % 3 == 0 and times == [float(f) for f in range(len(times))]
    assert stage.GetEndTimeCode() == times[-1]
    for f in range(len(times)):
        np.testing.assert_array_equal(np.array(attr.Get(f)), base * np.float32(1 + f))
    assert validation_errors(stage) == []


_INTERRUPTED_WRITER = """
import signal
import sys
import numpy as np
signal.signal(signal.SIGINT, signal.default_int_handler)  # as at a terminal, even where the runner ignores SIGINT
from warpfem.io.usd import UsdWriter
n = 1000
base = np.random.default_rng(2).normal(size=(n, 3)).astype(np.float32)
faces = np.arange(3 * n).reshape(n, 3) % n
try:
    with UsdWriter(sys.argv[1], [("m", faces)], fps=60.0, save_every=None, chunk_bytes=3 * 12 * n, workers=2) as w:
        for f in range(10**9):
            w.add_frame(f, [base * np.float32(1 + f)])
            if f == 30:
                print("writing", flush=True)
except KeyboardInterrupt:
    print(w.frames_added, flush=True)
"""


def test_ctrl_c_at_the_terminal_keeps_every_frame_added(tmp_path):
    """SIGINT to the whole process group, as a terminal's Ctrl-C sends it: the writer processes are not
    stopped by it, and the file holds every frame added, each as given."""
    import signal
    import subprocess
    import sys

    from pxr import Usd, UsdGeom

    path = tmp_path / "stopped.usdc"
    cmd = [sys.executable, "-c", _INTERRUPTED_WRITER, str(path)]
    child = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    assert child.stdout.readline() == "writing\n", child.stderr.read()
    writers = _children(child.pid)
    os.killpg(child.pid, signal.SIGINT)
    try:
        out, err = child.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        for pid in [child.pid, *writers]:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        child.communicate()
        raise
    assert child.returncode == 0, err
    added = int(out.split()[-1])
    base = np.random.default_rng(2).normal(size=(1000, 3)).astype(np.float32)
    stage = Usd.Stage.Open(str(path))
    attr = UsdGeom.Mesh(stage.GetPrimAtPath("/World/m")).GetPointsAttr()
    times = attr.GetTimeSamples()
    assert len(times) >= added > 30 and times == [float(f) for f in range(len(times))]
    assert stage.GetEndTimeCode() == times[-1]
    for f in range(len(times)):
        np.testing.assert_array_equal(np.array(attr.Get(f)), base * np.float32(1 + f))
    assert not any(".tmp-" in p.name for p in (tmp_path / "stopped.clips").iterdir())
    assert writers and not any(map(_alive, writers))


_INTERRUPTED_INSIDE = """
import signal
import sys
import numpy as np
signal.signal(signal.SIGINT, signal.default_int_handler)  # as at a terminal, even where the runner ignores SIGINT
from warpfem.io.usd import UsdWriter
n = 1000
base = np.random.default_rng(2).normal(size=(n, 3)).astype(np.float32)
faces = np.arange(3 * n).reshape(n, 3) % n
w = UsdWriter(sys.argv[1], [("m", faces)], fps=60.0, save_every=None, chunk_bytes=3 * 12 * n, workers=2)
method = getattr(w._pool, sys.argv[2])
calls = []

def interrupted(*args, **kwargs):
    out = method(*args, **kwargs)
    if out != []:  # a chunk sent, or chunks reported exported
        calls.append(1)
        if len(calls) == 3:  # one Ctrl-C (a second would stop the writer at once, by design)
            signal.raise_signal(signal.SIGINT)
    return out

setattr(w._pool, sys.argv[2], interrupted)
try:
    with w:
        for f in range(200):
            w.add_frame(f, [base * np.float32(1 + f)])
except KeyboardInterrupt:
    print(w.frames_added, flush=True)
"""


@pytest.mark.parametrize("where", ["done", "cut"])
def test_ctrl_c_inside_the_writer_keeps_every_frame_added(tmp_path, where):
    """Ctrl-C landing just after the writer read its processes' messages, or just after it sent a chunk
    for export (where a stop used to lose a message and wait forever, or export a chunk twice): the run
    stops at once and the file holds every frame added."""
    import signal
    import subprocess
    import sys

    from pxr import Usd, UsdGeom

    path = tmp_path / "stopped.usdc"
    child = subprocess.Popen(
        [sys.executable, "-c", _INTERRUPTED_INSIDE, str(path), where],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        out, err = child.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        os.killpg(child.pid, signal.SIGKILL)
        child.communicate()
        raise
    assert child.returncode == 0, err
    added = int(out.split()[-1])
    assert 0 < added < 200
    stage = Usd.Stage.Open(str(path))
    attr = UsdGeom.Mesh(stage.GetPrimAtPath("/World/m")).GetPointsAttr()
    assert attr.GetTimeSamples() == [float(f) for f in range(added)]
    base = np.random.default_rng(2).normal(size=(1000, 3)).astype(np.float32)
    np.testing.assert_array_equal(np.array(attr.Get(added - 1)), base * np.float32(added))


@pytest.mark.parametrize("workers", [0, 2], ids=["inline", "2 writer processes"])
def test_a_failed_export_reaches_the_caller_and_stops_the_writer(tmp_path, workers):
    """The clips folder replaced by a file under a running writer: the next export fails, the caller gets an
    OSError naming the chunk file, and no writer process or temporary file is left."""
    import shutil

    bodies, frames = bodies_and_frames(8)
    before = set(_children())
    writer = UsdWriter(tmp_path / "x.usdc", bodies, fps=60.0, chunk_bytes=1, save_every=None, workers=workers)
    started = set(_children()) - before
    writer.add_frame(0, frames[0])
    writer.save()
    shutil.rmtree(tmp_path / "x.clips")
    (tmp_path / "x.clips").write_text("not a folder")
    with pytest.raises(OSError, match=r"x\.00000\d\.tmp-\d+\.usdc: USD export failed"):
        with writer:
            for f in range(1, 8):
                writer.add_frame(f, frames[f])
    assert not any(map(_alive, started))
    assert not any(".tmp-" in p.name for p in tmp_path.iterdir())


def test_a_clips_folder_is_replaced_only_if_ours(tmp_path):
    from pxr import Usd, UsdGeom

    bodies, frames = bodies_and_frames(4)
    path = tmp_path / "x.usdc"
    with UsdWriter(path, bodies, fps=60.0, chunk_bytes=1) as writer:  # a clip per frame
        for f, points in enumerate(frames):
            writer.add_frame(f, points)
    assert len(list((tmp_path / "x.clips").glob("x.*.usdc"))) == 4
    killed = tmp_path / ".x.clips.old-1-2"  # what a run killed while deleting old clips leaves
    killed.mkdir()
    (killed / "x.000000.usdc").write_bytes(b"old")
    with UsdWriter(path, bodies, fps=60.0, chunk_bytes=2 * 12 * 14) as writer:  # ours: replaced
        for f, points in enumerate(frames[:3]):
            writer.add_frame(f, points)
    assert len(list((tmp_path / "x.clips").glob("x.*.usdc"))) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.clips", "x.usdc"]  # the old clips deleted beside
    with UsdWriter(path, bodies, fps=60.0) as writer:  # one file now: our old clips go
        writer.add_frame(0, frames[0])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.usdc"]
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.Mesh(stage.GetPrimAtPath("/World/tet")).GetPointsAttr().GetTimeSamples() == [0.0]

    foreign = tmp_path / "y.clips"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="exists"):
        UsdWriter(tmp_path / "y.usdc", bodies, fps=60.0, overwrite=False)
    writer = UsdWriter(tmp_path / "y.usdc", bodies, fps=60.0, chunk_bytes=1)
    with pytest.raises(FileExistsError, match="y.clips"):
        writer.add_frame(0, frames[0])
    writer.abort()
    assert (foreign / "notes.txt").read_text() == "mine" and not (tmp_path / "y.usdc").exists()


def test_prop_transforms_are_checked_per_frame(tmp_path):
    prop = Prop("obstacles/r", np.eye(3), np.array([[0, 1, 2]]))
    writer = UsdWriter(tmp_path / "x.usdc", [("a", np.array([[0, 1, 2]]))], fps=60.0, props=[prop])
    with pytest.raises(ValueError, match="a transform for each of 1 moving props, got 0"):
        writer.add_frame(0, [np.eye(3)])
    with pytest.raises(ValueError, match="finite 4x4"):
        writer.add_frame(0, [np.eye(3)], [np.full((4, 4), np.nan)])
    writer.abort()
    assert list(tmp_path.iterdir()) == []
    still = Prop("obstacles/s", np.eye(3), np.array([[0, 1, 2]]), matrix=np.eye(4))
    writer = UsdWriter(tmp_path / "x.usdc", [("a", np.array([[0, 1, 2]]))], fps=60.0, props=[prop, still])
    with pytest.raises(ValueError, match="a transform for each of 1 moving props, got 2"):
        writer.add_frame(0, [np.eye(3)], [np.eye(4), np.eye(4)])  # none for the still prop
    writer.abort()
    bad = Prop("obstacles/s", np.eye(3), np.array([[0, 1, 2]]), matrix=np.full((4, 4), np.inf))
    with pytest.raises(ValueError, match="finite 4x4"):
        UsdWriter(tmp_path / "x.usdc", [("a", np.array([[0, 1, 2]]))], fps=60.0, props=[bad])
    assert list(tmp_path.iterdir()) == []


def test_no_writer_process_where_python_cannot_be_started_again(monkeypatch, tmp_path):
    """Inside an application embedding Python, ``sys.executable`` is the application: the writer stays inline."""
    import sys

    from warpfem.io import usd_workers

    monkeypatch.setattr(sys, "executable", "/opt/app/bin/app")
    assert usd_workers.default_workers() == 0
    bodies, frames = bodies_and_frames(2)
    before = _children()
    with UsdWriter(tmp_path / "x.usdc", bodies, fps=60.0) as writer:
        assert _children() == before
        writer.add_frame(0, frames[0])
    assert (tmp_path / "x.usdc").is_file()


@pytest.mark.parametrize("n", [1, 5, 63, 64, 65, 1000, 97_602])
def test_extent_bounds_agree_with_numpy(n):
    """The extent's corners, reduced in blocks, equal NumPy's plain min and max over the points, also for a
    strided view and with a NaN (which shows in the corners)."""
    from warpfem.io.penetration import bounds

    p = np.random.default_rng(n).normal(size=(n, 3)).astype(np.float32)
    for q in (p, np.asfortranarray(p), p[::-1]):
        lo, hi = bounds(q)
        np.testing.assert_array_equal(lo, q.min(axis=0))
        np.testing.assert_array_equal(hi, q.max(axis=0))
    p[n // 2, 1] = np.nan
    lo, hi = bounds(p)
    assert np.isnan(lo[1]) and np.isnan(hi[1]) and np.isfinite(lo[[0, 2]]).all()


def test_writer_processes_only_for_large_frames(monkeypatch):
    """On 16 cores, 4 processes for a 20 MB frame; a 1 MB frame (the default scene's) is written inline."""
    import os

    from warpfem.io import usd_workers

    monkeypatch.setattr(os, "sched_getaffinity", lambda _pid: set(range(16)), raising=False)
    assert usd_workers.default_workers(20 * 2**20) == 4
    assert usd_workers.default_workers(2**20) == 0
    assert usd_workers.default_workers() == 4


def test_a_runs_prop_transforms_are_the_simulations_matrices(tmp_path):
    """The transforms a run writes each frame (worked out without building the props' meshes, a block of frames
    at a time) are the matrices of ``obstacles_at`` and ``handles_at``: a keyed box, a still sphere and a keyed,
    turning handle."""
    import trimesh

    import warpfem
    from warpfem.runner import _by_frame, _props

    trimesh.creation.icosphere(subdivisions=2).export(tmp_path / "ball.obj")
    (tmp_path / "scene.toml").write_text(
        '[scene]\nframes = 4\n\n[[object]]\nname = "ball"\nmesh = "ball.obj"\nfaces = 120\nscale = 0.2\n\n'
        '[[obstacle]]\nkind = "box"\ncenter = [0.0, -0.5, 0.0]\nhalf_extents = [0.5, 0.1, 0.5]\n'
        "keys = [[0.0, 0, 0, 0, 0, 0, 0], [0.1, 0.0, 0.3, 0.0, 0, 0, 0]]\n\n"
        '[[obstacle]]\nkind = "sphere"\ncenter = [2.0, 0.0, 0.0]\nradius = 0.25\n\n'
        '[[handle]]\nname = "top"\nobject = "ball"\nmin = [-1.0, 0.1, -1.0]\nmax = [1.0, 1.0, 1.0]\n'
        "keys = [[0.0, 0, 0, 0, 0, 0, 0], [0.05, 0.1, 0.0, 0.0, 0, 0, 90]]\n"
    )
    scene = warpfem.load_scene(tmp_path / "scene.toml")
    sim = warpfem.Simulation(scene, device="cpu", cache_dir=os.environ.get("WARPFEM_CACHE") or tmp_path)
    props, poses = _props(sim)
    assert [p.path for p in props] == ["obstacles/obstacle0", "obstacles/obstacle1", "handles/top"]
    assert [p.matrix is None for p in props] == [True, False, True]  # the still sphere's transform is fixed
    for time in (0.0, 0.02, 0.07, 0.5):
        posed = [*sim.obstacles_at(time), *sim.handles_at(time)]
        np.testing.assert_array_equal(np.array(poses(time)), np.array([posed[0].matrix, posed[2].matrix]))
        np.testing.assert_array_equal(props[1].matrix, posed[1].matrix)
    assert not np.allclose(poses(0.03)[1][:3, :3], np.eye(3))  # the handle turns
    by_frame = _by_frame(poses, 60.0, 3)  # what the writer's thread takes: frames 0, 3, ... and the last
    for frame in (0, 3, 6, 190, 192, 200, 201):
        np.testing.assert_array_equal(np.array(by_frame(frame)), np.array(poses(frame / 60.0)))


def test_a_one_chunk_file_streamed_holds_what_a_writer_process_exports(tmp_path):
    """A run of one chunk, streamed and closed with its topology and metadata (its samples not written again),
    holds exactly the layer a writer process authors with usd-core and exports from the same frames, moving and
    still props and a guide included (usd-core's text of both), and is a valid stage."""
    from pxr import Sdf, Usd

    bodies, frames = bodies_and_frames(6)
    rng = np.random.default_rng(1)
    big = rng.integers(0, 40, size=(30, 3))  # faces past the 16 values where crate arrays may be compressed
    bodies.append(("big", big))
    frames = [[*points, rng.normal(size=(40, 3))] for points in frames]
    box = Prop("obstacles/box", np.eye(3), np.array([[0, 1, 2]]))
    grip = Prop("handles/left/grip", rng.normal(size=(20, 3)), rng.integers(0, 20, size=(25, 3)), guide=True)
    still = Prop("still/wall", np.eye(3), np.array([[0, 2, 1]]), matrix=np.arange(16.0).reshape(4, 4))
    texts = []
    for workers in (0, 1):
        path = tmp_path / f"w{workers}.usdc"
        with UsdWriter(path, bodies, fps=24.0, up_axis="Z", props=[box, still, grip], workers=workers) as writer:
            for f, points in enumerate(frames):
                writer.add_frame(f, points, [np.diag([1.0, 2.0, 3.0, 1.0]) + f, np.eye(4) * (f + 1)])
        texts.append(Sdf.Layer.OpenAsAnonymous(str(path)).ExportToString())
        assert validation_errors(Usd.Stage.Open(str(path))) == []
    assert texts[0] == texts[1]


@pytest.mark.parametrize("workers", [0, 2], ids=["inline", "2 writer processes"])
@pytest.mark.parametrize("ext", [".usdc", ".usda"])
@pytest.mark.parametrize("final", [5, 3, 9], ids=["the last frame added", "too early", "never reached"])
def test_a_top_level_layer_written_ahead_is_the_one_closing_exports(tmp_path, monkeypatch, ext, workers, final):
    """With ``final_frame`` the top-level layer is written ahead as each chunk opens, and closing only moves it
    into place where it holds: the file is byte for byte the one written without it, whether the hint holds or
    not, and no temporary file is left."""
    import warpfem.io.usd as usd

    exported = []
    export = usd.export
    monkeypatch.setattr(usd, "export", lambda layer, path: (exported.append(path.name), export(layer, path))[1])
    bodies, frames = bodies_and_frames(6)
    files = []
    for hint in (None, final):
        folder = tmp_path / str(hint)
        folder.mkdir()
        exported.clear()
        with UsdWriter(folder / f"out{ext}", bodies, fps=30.0, chunk_bytes=300, workers=workers, final_frame=hint) as w:
            for f, points in enumerate(frames):
                w.add_frame(f, points)
        assert [p.name for p in folder.rglob("*") if ".tmp-" in p.name] == []
        files.append((folder / f"out{ext}").read_bytes())
        assert len(list((folder / "out.clips").glob("out.*.usdc"))) == 3
        tops = [name for name in exported if "-final" not in name]
        assert len(tops) == (3 if hint in (None, 9) else 2)  # one moved into place where the hint came true
    assert files[0] == files[1]


@pytest.mark.parametrize("ext", [".usdc", ".usda"])
def test_a_chunk_streamed_into_a_crate_grows_past_the_exported_size(tmp_path, ext):
    """Streamed on the calling thread into a crate, 36 MB of frames stay one file (nothing is held in memory or
    exported again at the end); a text target is exported by usd-core, so it is cut at the exported size.
    Either way every frame reads back."""
    from pxr import Usd, UsdGeom

    from warpfem.io.usd import CHUNK_BYTES, STREAMED_CHUNK_BYTES

    n, frames = 300_000, 10
    assert frames * 12 * n > CHUNK_BYTES and frames * 12 * n < STREAMED_CHUNK_BYTES
    faces = np.arange(3 * (n // 3)).reshape(-1, 3)
    path = tmp_path / f"big{ext}"
    with UsdWriter(path, [("m", faces)], fps=60.0, save_every=None, workers=0) as writer:
        base = np.random.default_rng(0).normal(size=(n, 3)).astype(np.float32)
        for f in range(frames):
            writer.add_frame(f, [base + f])
    assert writer.clips_dir.exists() == (ext == ".usda")
    stage = Usd.Stage.Open(str(path))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/m"))
    for f in (0, 3, frames - 1):
        np.testing.assert_array_equal(np.asarray(mesh.GetPointsAttr().Get(f)), base + f)

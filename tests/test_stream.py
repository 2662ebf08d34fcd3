"""FrameStream: frames handed to consumers on a background thread, in order, each with its own points."""

from __future__ import annotations

import os
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest
import warp as wp

from warpfem.io.stream import FrameStream


class _FakeSim:
    """Two bodies of 3 and 5 dense points whose positions are the number of frames mapped so far."""

    def __init__(self, device: str) -> None:
        self.device = wp.get_device(device)
        bodies = [SimpleNamespace(dense_start=0, dense_count=3), SimpleNamespace(dense_start=3, dense_count=5)]
        self.model = SimpleNamespace(bodies=bodies, dense_count=8)
        self.dense = wp.zeros(8, dtype=wp.vec3, device=device)
        self.mapped = 0

    def map_dense(self) -> wp.array:
        self.dense.fill_(float(self.mapped))
        self.mapped += 1
        return self.dense


def test_every_frame_reaches_every_consumer_in_order_with_its_points(device):
    sim = _FakeSim(device)
    seen: list[tuple[str, int, list[np.ndarray]]] = []
    threads = set()

    def consumer(name):
        def take(frame, points, boxes):
            threads.add(threading.current_thread().name)
            time.sleep(0.002)  # slower than the producer: the stream must wait, not drop or mix frames
            seen.append((name, frame, [p.copy() for p in points]))

        return take

    with FrameStream(sim, [("a", consumer("a")), ("b", consumer("b"))]) as stream:
        for frame in range(0, 40, 2):
            stream.submit(frame)
    for name in "ab":
        assert [f for n, f, _ in seen if n == name] == list(range(0, 40, 2))
    for _, frame, points in seen:
        assert [p.shape for p in points] == [(3, 3), (5, 3)]
        assert all((p == frame // 2).all() for p in points)
    assert threads == {"warpfem-a", "warpfem-b"}
    assert stream.seconds["a"] >= 20 * 0.002 and stream.seconds["b"] >= 20 * 0.002
    assert 0 < stream.cpu_seconds["a"] < stream.seconds["a"] / 2  # sleeping takes no CPU


def test_a_skippable_consumer_behind_takes_the_newest_frame_and_always_the_last(device):
    """A slow skippable consumer skips frames (counted) without holding up the stream; the other takes all;
    every frame a consumer takes carries its own points; the last frame reaches both."""
    sim = _FakeSim(device)
    taken: dict[str, list[int]] = {"all": [], "some": []}

    def take(name, delay):
        def consume(frame, points, boxes):
            time.sleep(delay)
            assert all((p == frame).all() for p in points)
            taken[name].append(frame)

        return consume

    with FrameStream(sim, [("all", take("all", 0.0)), ("some", take("some", 0.01))], skippable=("some",)) as stream:
        for frame in range(60):
            stream.submit(frame)
            time.sleep(0.001)
    assert taken["all"] == list(range(60))
    assert taken["some"] == sorted(taken["some"]) and taken["some"][-1] == 59
    assert stream.skipped["some"] == 60 - len(taken["some"]) > 0 and stream.skipped["all"] == 0


def test_consumers_run_alongside_each_other(device):
    """Two consumers of 20 ms a frame over 10 frames take about 0.2 s together, not 0.4 s one after the other."""
    sim = _FakeSim(device)
    slow = [("a", lambda frame, *_: time.sleep(0.02)), ("b", lambda frame, *_: time.sleep(0.02))]
    clock = time.perf_counter()
    with FrameStream(sim, slow) as stream:
        for frame in range(10):
            stream.submit(frame)
    assert time.perf_counter() - clock < 0.3
    assert stream.seconds["a"] >= 0.2 and stream.seconds["b"] >= 0.2


def test_a_consumer_error_reaches_the_caller_and_stops_the_stream(device):
    sim = _FakeSim(device)
    taken = []

    def failing(frame, points, boxes):
        if frame == 3:
            raise OSError("disk full")
        taken.append(frame)

    with pytest.raises(OSError, match="disk full"):
        with FrameStream(sim, [("write", failing)]) as stream:
            for frame in range(100):
                stream.submit(frame)
                time.sleep(0.001)
    assert taken == [0, 1, 2]


def test_an_exception_in_the_caller_still_hands_over_the_frames_submitted(device):
    sim = _FakeSim(device)
    taken = []
    with pytest.raises(KeyboardInterrupt):
        with FrameStream(sim, [("write", lambda frame, *_: taken.append(frame))]) as stream:
            for frame in range(5):
                stream.submit(frame)
            raise KeyboardInterrupt
    assert taken == [0, 1, 2, 3, 4]


def test_each_frame_carries_its_bodies_boxes_and_a_non_finite_point_makes_its_box_infinite(device):
    """The boxes reduced on the device equal NumPy's min and max of each body's points; a NaN in one body
    makes that body's box infinite both ways (a reader of the box alone sees it) and leaves the other's."""
    sim = _FakeSim(device)
    rng = np.random.default_rng(3)
    frames = [rng.normal(size=(8, 3)).astype(np.float32) for _ in range(4)]
    frames[2][4, 1] = np.nan  # body 1 (points 3..7) of frame 2
    seen = {}

    def map_dense():
        sim.dense.assign(frames[sim.mapped])
        sim.mapped += 1
        return sim.dense

    sim.map_dense = map_dense
    with FrameStream(sim, [("boxes", lambda frame, points, boxes: seen.update({frame: boxes.copy()}))]) as stream:
        for frame in range(4):
            stream.submit(frame)
    for frame, points in enumerate(frames):
        for body, (start, end) in enumerate([(0, 3), (3, 8)]):
            if frame == 2 and body == 1:
                np.testing.assert_array_equal(seen[frame][body], [[-np.inf] * 3, [np.inf] * 3])
            else:
                want = [points[start:end].min(axis=0), points[start:end].max(axis=0)]
                np.testing.assert_array_equal(seen[frame][body], want)


@pytest.mark.parametrize("writers", [0, 2], ids=["inline", "2 writer processes"])
def test_a_run_in_clips_reads_back_the_simulated_positions_at_every_frame(device, tmp_path, monkeypatch, writers):
    """The golden two balls, a chunk per frame: every frame of the written clip set equals the positions the
    simulation held at that frame (read on the calling thread, synchronously), on the run's device, with the
    chunks written on the writer's thread or by writer processes."""
    from pathlib import Path

    from pxr import Usd, UsdGeom

    import warpfem
    import warpfem.io.usd
    from warpfem.runner import record

    monkeypatch.setattr(warpfem.io.usd, "default_workers", lambda *_: writers)

    root = Path(__file__).resolve().parents[1]
    scene = warpfem.load_scene(root / "tests" / "data" / "golden" / "two_balls.toml").with_frames(12)
    sim = warpfem.Simulation(scene, device=device, cache_dir=os.environ.get("WARPFEM_CACHE") or tmp_path)
    held = {}
    out = tmp_path / "a.usdc"
    stream = sim.device.stream if sim.device.is_cuda else None
    summary = record(sim, out, save_every=0.0, on_points=lambda frame, points: held.__setitem__(frame, points))
    if stream is not None:  # the writer's and the check's threads left the device's current stream alone
        assert sim.device.stream is stream
    assert sorted(held) == list(range(13))
    assert len(list((tmp_path / "a.clips").glob("a.*.usdc"))) == 13
    stage = Usd.Stage.Open(str(out))
    for i, name in enumerate(sim.body_names):
        attr = UsdGeom.Mesh(stage.GetPrimAtPath(f"/World/{name}")).GetPointsAttr()
        assert attr.GetTimeSamples() == [float(f) for f in range(13)]
        for frame, points in held.items():
            np.testing.assert_array_equal(np.array(attr.Get(frame)), points[i].astype(np.float32))
    s = summary.seconds
    assert s["wall"] > 0 and s["write"] > 0 and summary.ms_per_frame == pytest.approx(1e3 * s["wall"] / 12)
    assert 0 < s["write_cpu"] <= s["write"] + 0.01
    assert s["write_workers"] > 0 and (summary.writer_peak_bytes > 0) == (writers > 0)


@pytest.mark.parametrize("save_every", [None, 0.0], ids=["one file", "a chunk per frame"])
def test_a_run_reports_its_close_and_its_file_is_complete_when_record_returns(device, tmp_path, save_every):
    """The writer finishes the file on its thread as the last frame comes: ``close`` (last hand-over to the
    file written) is part of the wall time, and the file read back holds every simulated frame to the last."""
    from pathlib import Path

    from pxr import Usd, UsdGeom

    import warpfem
    from warpfem.runner import record

    root = Path(__file__).resolve().parents[1]
    scene = warpfem.load_scene(root / "tests" / "data" / "golden" / "two_balls.toml").with_frames(6)
    sim = warpfem.Simulation(scene, device=device, cache_dir=os.environ.get("WARPFEM_CACHE") or tmp_path)
    held = {}
    out = tmp_path / "a.usdc"
    summary = record(sim, out, save_every=save_every, on_points=lambda frame, points: held.__setitem__(frame, points))
    s = summary.seconds
    assert 0 <= s["close"] <= s["wall"]
    assert (tmp_path / "a.clips").is_dir() == (save_every is not None)
    stage = Usd.Stage.Open(str(out))
    assert stage.GetEndTimeCode() == 6.0
    for i, name in enumerate(sim.body_names):
        attr = UsdGeom.Mesh(stage.GetPrimAtPath(f"/World/{name}")).GetPointsAttr()
        assert attr.GetTimeSamples() == [float(f) for f in range(7)]
        for frame, points in held.items():
            np.testing.assert_array_equal(np.array(attr.Get(frame)), points[i].astype(np.float32))

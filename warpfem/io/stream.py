"""Frames handed from the device to the file on background threads, while the next frames simulate.

Each frame's dense points are mapped on the device, each body's bounding box reduced there, and both
copied asynchronously into one of a few pinned host buffers; each consumer (the USD writer, the penetration
check) has a thread of its own that waits for the copy and takes the frames in order; a buffer is free again
once every consumer is done with it. The simulation waits only when every buffer is taken, i.e. when a
consumer is more than a few frames behind. The boxes spare the consumers' threads a pass over the points
each (the extents the writer samples, the ground's lowest point), work that holds the interpreter lock
the stepping thread needs.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import warp as wp

from warpfem.io.penetration import BodyBounds

QUEUE_BYTES = 768 << 20
"""Pinned host memory for frames in flight (bytes); at least :data:`MIN_SLOTS` frames whatever their size.
Enough for several frames of a large scene, whose writer processes keep up on average but not frame by frame
(docs/performance.md)."""

MIN_SLOTS = 2
MAX_SLOTS = 8

Consumer = Callable[[int, list[np.ndarray], np.ndarray], None]
"""Called as ``consumer(frame, points, boxes)``: one (n_i, 3) float32 view per body and a (bodies, 2, 3) array of
their lower and upper corners (infinite both ways for a body with a non-finite point), valid during the call."""


class FrameStream:
    """Streams a simulation's dense frames to consumers, each on a background thread of its own.

    Args:
        sim: A :class:`~warpfem.simulation.Simulation` (anything with ``map_dense()``, ``model`` and ``device``).
        consumers: ``(name, consumer)`` pairs, each called for every frame in order on its thread
            (``warpfem-<name>``); their wall time is summed per name in :attr:`seconds`.
        skippable: Names of consumers that, when frames wait for them, take the newest and skip the others
            (the last frame always), so that they never hold the simulation up; :attr:`skipped` counts them.

    Use as a context manager: leaving the block waits until every submitted frame is consumed, then raises
    the first consumer error if there was one (a consumer error also stops further submits). The threads
    wait on the device, so no CUDA graph capture may run on it meanwhile (``Simulation.capture`` first).

    Attributes:
        seconds: Wall time per consumer name (s), spent on its thread.
        cpu_seconds: CPU time of each consumer's calls (s): its wall time less the waits for the interpreter
            lock (held by the other threads) and for a core.
        skipped: Frames each consumer skipped (only a ``skippable`` one skips).
        waited: Wall time the caller spent waiting for a free buffer (s).
        on_device: The last submitted frame's dense points and boxes on the device (the flat ``wp.vec3``
            arrays, valid until the next submit); None before the first.
    """

    def __init__(self, sim: Any, consumers: Sequence[tuple[str, Consumer]], skippable: Sequence[str] = ()) -> None:
        model = sim.model
        self._sim, self._consumers = sim, list(consumers)
        self._skippable = set(skippable)
        self._cuda = sim.device.is_cuda
        self._ranges = [(b.dense_start, b.dense_start + b.dense_count) for b in model.bodies]
        self._bounds = BodyBounds(self._ranges, sim.device)
        frame_bytes = max(12 * model.dense_count, 1)
        count = min(MAX_SLOTS, max(MIN_SLOTS, QUEUE_BYTES // frame_bytes))
        self._free: queue.Queue[int] = queue.Queue()
        self._work: list[queue.Queue[tuple[int, int] | None]] = [queue.Queue() for _ in self._consumers]
        self._users = [0] * count  # consumers not yet done with each buffer
        self._lock = threading.Lock()
        self._slots = [
            wp.empty(model.dense_count, dtype=wp.vec3, device="cpu", pinned=self._cuda) for _ in range(count)
        ]
        self._boxes = [
            wp.empty(2 * len(self._ranges), dtype=wp.vec3, device="cpu", pinned=self._cuda) for _ in range(count)
        ]
        flats = [slot.numpy() for slot in self._slots]  # each slot's host views, made once
        self._views = [[flat[start:end] for start, end in self._ranges] for flat in flats]
        self._box_views = [boxes.numpy().reshape(-1, 2, 3) for boxes in self._boxes]
        self._events = [wp.Event(sim.device) if self._cuda else None for _ in range(count)]
        self._stream = sim.device.stream if self._cuda else None
        for i in range(count):
            self._free.put(i)
        self.seconds = {name: 0.0 for name, _ in self._consumers}
        self.cpu_seconds = {name: 0.0 for name, _ in self._consumers}
        self.skipped = {name: 0 for name, _ in self._consumers}
        self.waited = 0.0
        self.on_device: tuple[wp.array, wp.array] | None = None
        self._error: BaseException | None = None
        self._threads = [
            threading.Thread(target=self._run, args=(i,), name=f"warpfem-{name}", daemon=True)
            for i, (name, _) in enumerate(self._consumers)
        ]
        for thread in self._threads:
            thread.start()

    def submit(self, frame: int) -> None:
        """Map the current state's dense points and queue frame ``frame`` (waits only if every buffer is taken).

        Raises:
            The first consumer error, if one happened (nothing more is queued then).
        """
        clock = time.perf_counter()
        slot = None
        while slot is None:
            self._raise_error()
            try:
                slot = self._free.get(timeout=0.1)
            except queue.Empty:
                continue
        self.waited += time.perf_counter() - clock
        dense = self._sim.map_dense()
        bounds = self._bounds.compute(dense)
        wp.copy(self._slots[slot], dense, stream=self._stream)
        wp.copy(self._boxes[slot], bounds, stream=self._stream)
        self.on_device = (dense, bounds)
        if self._cuda:
            self._stream.record_event(self._events[slot])
        self._users[slot] = len(self._work)
        for work in self._work:
            work.put((frame, slot))

    def close(self) -> None:
        """Wait until every queued frame is consumed and stop the threads; raise the first consumer error."""
        for work, thread in zip(self._work, self._threads, strict=True):
            if thread.is_alive():
                work.put(None)
        for thread in self._threads:
            thread.join()
        self._raise_error()

    def _raise_error(self) -> None:
        if self._error is not None:
            error, self._error = self._error, None
            raise error

    def _run(self, index: int) -> None:
        """Consumer ``index``'s thread: its frames in order until the end mark; after any error, only drain."""
        name, consume = self._consumers[index]
        work, done = self._work[index], False
        while not done and (item := work.get()) is not None:
            if name in self._skippable:
                item, done = self._newest(name, item, work)
            frame, slot = item
            try:
                if self._error is None:
                    if self._cuda:
                        wp.synchronize_event(self._events[slot])
                    clock, cpu = time.perf_counter(), time.thread_time()
                    consume(frame, list(self._views[slot]), self._box_views[slot])
                    self.seconds[name] += time.perf_counter() - clock
                    self.cpu_seconds[name] += time.thread_time() - cpu
            except BaseException as err:  # handed to the simulating thread at its next submit or close
                with self._lock:
                    self._error = self._error or err
            finally:
                self._release(slot)

    def _newest(self, name: str, item: tuple[int, int], work: queue.Queue) -> tuple[tuple[int, int], bool]:
        """The newest frame queued for consumer ``name`` from ``item`` on, and whether the end mark followed it.

        The frames passed over are released and counted as skipped.
        """
        while True:
            try:
                following = work.get_nowait()
            except queue.Empty:
                return item, False
            if following is None:
                return item, True
            self._release(item[1])
            self.skipped[name] += 1
            item = following

    def _release(self, slot: int) -> None:
        """One consumer is done with buffer ``slot``: free it when it was the last."""
        with self._lock:
            self._users[slot] -= 1
            last = self._users[slot] == 0
        if last:
            self._free.put(slot)

    def __enter__(self) -> FrameStream:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is None:
            self.close()
            return
        try:  # keep the frames finished before the exception; it is the one that propagates
            self.close()
        except Exception:
            pass

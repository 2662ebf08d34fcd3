"""Frames handed from the device to the file on a background thread, while the next frames simulate.

Each frame's dense points are mapped on the device and copied asynchronously into one of a few pinned
host buffers; a thread waits for the copy, hands the points to the consumers (the USD writer, the
penetration check) and frees the buffer. The simulation waits only when every buffer is taken, i.e. when
the writer is more than a few frames behind.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import warp as wp

QUEUE_BYTES = 256 << 20
"""Pinned host memory for frames in flight (bytes); at least :data:`MIN_SLOTS` frames whatever their size."""

MIN_SLOTS = 2
MAX_SLOTS = 8

Consumer = Callable[[int, list[np.ndarray]], None]
"""Called as ``consumer(frame, points)``: one (n_i, 3) float32 view per body, valid during the call only."""


class FrameStream:
    """Streams a simulation's dense frames to consumers on a background thread.

    Args:
        sim: A :class:`~warpfem.simulation.Simulation` (anything with ``map_dense()``, ``model`` and ``device``).
        consumers: ``(name, consumer)`` pairs called in order for every frame; their wall time is summed
            per name in :attr:`seconds`.

    Use as a context manager: leaving the block waits until every submitted frame is consumed, then raises
    the first consumer error if there was one (a consumer error also stops further submits). The thread
    waits on the device, so no CUDA graph capture may run on it meanwhile (``Simulation.capture`` first).

    Attributes:
        seconds: Wall time per consumer name (s), spent on the background thread.
        waited: Wall time the caller spent waiting for a free buffer (s).
    """

    def __init__(self, sim: Any, consumers: Sequence[tuple[str, Consumer]]) -> None:
        model = sim.model
        self._sim, self._consumers = sim, list(consumers)
        self._cuda = sim.device.is_cuda
        self._ranges = [(b.dense_start, b.dense_start + b.dense_count) for b in model.bodies]
        frame_bytes = max(12 * model.dense_count, 1)
        count = min(MAX_SLOTS, max(MIN_SLOTS, QUEUE_BYTES // frame_bytes))
        self._free: queue.Queue[int] = queue.Queue()
        self._work: queue.Queue[tuple[int, int] | None] = queue.Queue()
        self._slots = [
            wp.empty(model.dense_count, dtype=wp.vec3, device="cpu", pinned=self._cuda) for _ in range(count)
        ]
        self._events = [wp.Event(sim.device) if self._cuda else None for _ in range(count)]
        self._stream = sim.device.stream if self._cuda else None
        for i in range(count):
            self._free.put(i)
        self.seconds = {name: 0.0 for name, _ in self._consumers}
        self.waited = 0.0
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="warpfem-writer", daemon=True)
        self._thread.start()

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
        wp.copy(self._slots[slot], self._sim.map_dense(), stream=self._stream)
        if self._cuda:
            self._stream.record_event(self._events[slot])
        self._work.put((frame, slot))

    def close(self) -> None:
        """Wait until every queued frame is consumed and stop the thread; raise the first consumer error."""
        if self._thread.is_alive():
            self._work.put(None)
            self._thread.join()
        self._raise_error()

    def _raise_error(self) -> None:
        if self._error is not None:
            error, self._error = self._error, None
            raise error

    def _run(self) -> None:
        """The background thread: consume frames in order until the end mark; after an error, only drain."""
        while (item := self._work.get()) is not None:
            frame, slot = item
            try:
                if self._error is None:
                    if self._cuda:
                        wp.synchronize_event(self._events[slot])
                    flat = self._slots[slot].numpy()
                    points = [flat[start:end] for start, end in self._ranges]
                    for name, consume in self._consumers:
                        clock = time.perf_counter()
                        consume(frame, points)
                        self.seconds[name] += time.perf_counter() - clock
            except BaseException as err:  # handed to the simulating thread at its next submit or close
                self._error = err
            finally:
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

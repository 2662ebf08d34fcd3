"""Where :class:`~warpfem.io.usd.UsdWriter`'s chunks are written: by writer processes, or streamed inline.

usd-core's export of a chunk runs at about 1 GB/s on one core and holds the interpreter lock, which the
simulation's threads need too. :class:`ProcessPool` hands each chunk to one of a few writer processes
(``python -m warpfem.io.usd_workers``), round robin, so chunks are authored and exported in parallel and
the calling process only copies each frame once, into a ring of shared-memory slots. Each process holds
at most the chunk it is building; its allocator keeps the freed chunk's pages for the next one. A writer
process runs in a session of its own, so a Ctrl-C at the terminal reaches only the caller, which decides
what to finish; it exits when its socket closes, the caller's death included. :class:`InlinePool` streams
each frame to its chunk's file on the calling thread instead (:mod:`warpfem.io.crate`).

Both tell the caller which chunks are written (to the temporary path it named) and the last frame each
holds; placing them is the caller's job, in order.
"""

from __future__ import annotations

import contextlib
import mmap
import os
import resource
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from multiprocessing.connection import Connection, wait
from pathlib import Path

import numpy as np

from warpfem.io.crate import CrateStream
from warpfem.io.usd_layers import (
    CLIP_FILES,
    Chunk,
    Prop,
    StageInfo,
    Topology,
    animated_attributes,
    complete_stream,
    export,
    export_single,
    topology,
    write_clip_files,
)

QUEUE_BYTES = 384 << 20
"""Shared memory for frames on their way to the writer processes (bytes); 2 to 8 frames whatever their size."""

MAX_WORKERS = 4


PROCESS_FRAME_BYTES = 8 * 2**20
"""Frames of fewer point bytes are written inline: processes pay only where one thread cannot keep up with
the run, and starting them costs more than they save on small frames (the measurement: docs/decisions.md)."""


def default_workers(frame_bytes: int | None = None) -> int:
    """Writer processes for this machine and frame size: a quarter of the usable cores, at most 4.

    0 (inline) for frames of fewer than :data:`PROCESS_FRAME_BYTES` point bytes (None: any size), with fewer
    than 4 cores (no core to spare: on 2 a process wrote no faster in a whole run, for more CPU and memory),
    where not POSIX, or where ``sys.executable`` is not a Python interpreter to start again (an application
    embedding Python).
    """
    if frame_bytes is not None and frame_bytes < PROCESS_FRAME_BYTES:
        return 0
    if os.name != "posix" or not Path(sys.executable or "-").name.lower().startswith("python"):
        return 0
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return min(MAX_WORKERS, cores // 4)


class _StagedClipFiles:
    """The clips folder's topology and manifest, written ahead into a hidden staging folder, moved in later."""

    _staged: Path | None = None

    def _stage(self, staging: Path) -> None:
        """Make ``staging`` the (empty) folder to write them into."""
        shutil.rmtree(staging, ignore_errors=True)  # a leftover of a killed process with this one's id
        staging.mkdir()
        self._staged = staging

    def _move_staged(self, folder: Path) -> None:
        """Move the staged files into ``folder`` and remove the staging folder."""
        for name in CLIP_FILES:
            os.replace(self._staged / name, folder / name)
        self._drop_staged()

    def _drop_staged(self) -> None:
        """Remove the staging folder, if there is one."""
        if self._staged is not None:
            shutil.rmtree(self._staged, ignore_errors=True)
            self._staged = None


class InlinePool(_StagedClipFiles):
    """Streams chunks to their files on the calling thread (no processes).

    A chunk's samples go to a hidden temporary file in ``folder`` as they come (:class:`~warpfem.io.crate.
    CrateStream`: plain writes, which let the simulation's threads run meanwhile); cutting it only adds its
    index tables and moves the file to the name the caller gives.

    Attributes:
        seconds: Time spent writing samples and cutting chunks (s).
        peak_bytes: 0 (no process of its own).
    """

    def __init__(self, names: Sequence[str], prop_paths: Sequence[str], folder: Path) -> None:
        self._attributes = animated_attributes(names, prop_paths)
        self._folder = folder
        self._streams: dict[int, CrateStream] = {}
        self._done: list[tuple[int, int]] = []
        self._topology: Topology | None = None
        self.seconds = 0.0
        self.peak_bytes = 0

    def stage_clip_files(self, staging: Path, bodies: Sequence[tuple[str, np.ndarray]], props: Sequence[Prop]) -> None:
        """Write the clips folder's topology and manifest ahead, into the hidden folder ``staging``.

        Their export then happens before the run steps, not on the writer's thread beside it; starting the
        clips only moves them. A run that stays one file drops them, and takes the topology worked out here.
        """
        self._stage(staging)
        try:
            self._topology = write_clip_files(staging, str(os.getpid()), bodies, props)
        except BaseException:
            self._drop_staged()
            raise

    def add(
        self,
        chunk: int,
        frame: int,
        points: Sequence[np.ndarray],
        matrices: Sequence[np.ndarray],
        extents: Sequence[np.ndarray],
    ) -> None:
        """Sample ``points``, their (2, 3) ``extents`` and ``matrices`` at ``frame`` in chunk number ``chunk``."""
        clock = time.perf_counter()
        if chunk not in self._streams:
            path = self._folder / f".warpfem-chunk-{chunk}.tmp-{os.getpid()}.usdc"
            self._streams[chunk] = CrateStream(path, self._attributes)
        values = [v for p, box in zip(points, extents, strict=True) for v in (p, box)]
        values += [m.T for m in matrices]  # USD: row vectors
        self._streams[chunk].add(float(frame), values)
        self.seconds += time.perf_counter() - clock

    def clip_files(self, folder: Path) -> None:
        """Move the staged topology and manifest into the clips folder ``folder``."""
        clock = time.perf_counter()
        self._move_staged(folder)
        self.seconds += time.perf_counter() - clock

    def cut(self, chunk: int, tmp: Path) -> None:
        """Complete chunk ``chunk`` and move it to ``tmp``."""
        clock = time.perf_counter()
        stream = self._streams.pop(chunk)
        _close_into(stream, tmp)
        self._done.append((chunk, int(stream.last_time)))
        self.seconds += time.perf_counter() - clock

    def single(
        self, chunk: int, tmp: Path, bodies: Sequence[tuple[str, np.ndarray]], props: Sequence[Prop], info: StageInfo
    ) -> None:
        """Write chunk ``chunk`` to ``tmp`` as a self-contained file.

        A crate ``tmp`` is the chunk's own file, closed with the topology and the metadata (its samples are
        not written again); any other format is exported by usd-core from the chunk's file, completed there.
        """
        from pxr import Sdf

        clock = time.perf_counter()
        stream = self._streams.pop(chunk)
        last = int(stream.last_time)
        try:
            if tmp.suffix.lower() != ".usda":
                complete_stream(stream, self._topology or topology(bodies, props), info, last)
                _close_into(stream, tmp)
            else:
                stream.close()
                layer = Sdf.Layer.OpenAsAnonymous(str(stream.path))
                if layer is None:
                    raise OSError(f"{stream.path}: usd-core could not read the chunk written")
                export_single(layer, tmp, bodies, props, info, last)
        finally:
            stream.discard()
            self._drop_staged()
        self._done.append((chunk, last))
        self.seconds += time.perf_counter() - clock

    def done(self, block: bool) -> list[tuple[int, int]]:
        """``(chunk, last frame)`` per chunk written since the last call (``block`` is moot: nothing is pending)."""
        done, self._done = self._done, []
        return done

    def stop(self) -> None:
        """Drop the staged clip files, if the clips never started."""
        self._drop_staged()

    def kill(self) -> None:
        """Remove the chunks being written and the staged clip files."""
        for stream in self._streams.values():
            stream.discard()
        self._streams.clear()
        self._drop_staged()


class ProcessPool(_StagedClipFiles):
    """Authors and exports chunks in ``workers`` writer processes, chunk ``c`` in process ``c % workers``.

    The processes start at once, so that they are ready by the first frame, whose size sets the slots of
    shared memory.

    Attributes:
        seconds: Time the processes spent authoring and exporting chunks, summed over them (s).
        peak_bytes: The largest peak resident memory of one process, as of its last chunk exported (bytes).
    """

    def __init__(self, names: Sequence[str], prop_paths: Sequence[str], workers: int) -> None:
        self._names, self._prop_paths, self._count = list(names), list(prop_paths), workers
        self._conns: list[Connection] = []
        self._procs: list[subprocess.Popen] = []
        self._ring: mmap.mmap | None = None
        self._slot_floats = 0
        self._free: list[int] = []
        self._done: list[tuple[int, int]] = []
        self._staged_ready = False  # the first process said the staged clip files are written
        self.seconds = 0.0
        self.peak_bytes = 0
        self._fd = os.memfd_create("warpfem-frames") if hasattr(os, "memfd_create") else _unlinked_file()
        path = os.pathsep.join(filter(None, [_PACKAGE_ROOT, os.environ.get("PYTHONPATH")]))
        env = {**os.environ, **_ALLOCATOR, "PYTHONPATH": path}
        for _ in range(workers):
            ours, theirs = socket.socketpair()
            command = [sys.executable, "-m", "warpfem.io.usd_workers", str(theirs.fileno()), str(self._fd)]
            with theirs:
                fds, quiet = (theirs.fileno(), self._fd), subprocess.DEVNULL  # stdout may carry the caller's JSON
                proc = subprocess.Popen(
                    command, pass_fds=fds, env=env, stdin=quiet, stdout=quiet, start_new_session=True
                )
            self._procs.append(proc)
            self._conns.append(Connection(ours.detach()))

    def _setup(self, points: Sequence[np.ndarray]) -> None:
        """Size the shared memory for frames like ``points`` and tell the processes."""
        ranges = np.cumsum([0] + [len(p) for p in points]).tolist()
        self._slot_floats = 3 * ranges[-1]
        slots = min(8, max(2, QUEUE_BYTES // max(4 * self._slot_floats, 1)))
        size = max(4 * self._slot_floats * slots, 1)
        os.ftruncate(self._fd, size)
        self._ring = mmap.mmap(self._fd, size)
        self._free = list(range(slots))
        for conn in self._conns:
            conn.send((self._names, self._prop_paths, ranges))

    def add(
        self,
        chunk: int,
        frame: int,
        points: Sequence[np.ndarray],
        matrices: Sequence[np.ndarray],
        extents: Sequence[np.ndarray] | None = None,
    ) -> None:
        """Copy ``points`` into a free slot (waiting for one) and send frame ``frame`` of chunk ``chunk``.

        ``extents``: the bodies' (2, 3) bounds, else the writer process reads them off the points.
        """
        if self._ring is None:
            self._setup(points)
        while not self._free:
            self._pump(block=True)
        slot = self._free.pop()
        view = np.frombuffer(self._ring, np.float32, self._slot_floats, 4 * self._slot_floats * slot)
        start = 0
        for p in points:
            view[start : start + p.size] = p.reshape(-1)
            start += p.size
        boxes = None if extents is None else np.asarray(extents)
        self._conns[chunk % self._count].send(("frame", chunk, frame, slot, list(matrices), boxes))

    def stage_clip_files(self, staging: Path, bodies: Sequence[tuple[str, np.ndarray]], props: Sequence[Prop]) -> None:
        """Have the first writer process write the clips folder's topology and manifest now, into ``staging``.

        It does so while the run is built, not when the first chunk is cut, when its export held up that
        process's frames and, behind them, the simulation's.
        """
        self._stage(staging)
        self._staged_ready = False
        self._conns[0].send(("stage", str(staging), str(os.getpid()), list(bodies), list(props)))

    def clip_files(self, folder: Path) -> None:
        """Move the staged topology and manifest into the clips folder ``folder`` once the process wrote them."""
        while not self._staged_ready:
            self._pump(block=True)
        self._move_staged(folder)

    def cut(self, chunk: int, tmp: Path) -> None:
        """Have chunk ``chunk`` exported to ``tmp`` (it is reported by :meth:`done` once it is there)."""
        self._conns[chunk % self._count].send(("cut", chunk, str(tmp)))

    def single(
        self, chunk: int, tmp: Path, bodies: Sequence[tuple[str, np.ndarray]], props: Sequence[Prop], info: StageInfo
    ) -> None:
        """Have chunk ``chunk`` exported to ``tmp`` as a self-contained file (topology and metadata added)."""
        self._conns[chunk % self._count].send(("single", chunk, str(tmp), list(bodies), list(props), info))

    def done(self, block: bool) -> list[tuple[int, int]]:
        """``(chunk, last frame)`` per chunk exported since the last call; ``block``: wait for a message first.

        Raises:
            OSError: A writer process failed (its message) or exited.
        """
        self._pump(block)
        done, self._done = self._done, []
        return done

    def _pump(self, block: bool) -> None:
        """Read every message waiting from the processes (with ``block``, wait for one first)."""
        for conn in wait(self._conns, None if block else 0):
            while True:
                try:
                    message = conn.recv()
                except EOFError:
                    proc = self._procs[self._conns.index(conn)]
                    raise OSError(f"USD writer process {proc.pid} exited (code {proc.wait()})") from None
                if message[0] == "free":
                    self._free.append(message[1])
                elif message[0] == "staged":
                    self._staged_ready = True
                elif message[0] == "done":
                    self._done.append(message[1:3])
                    self.seconds += message[3]
                    self.peak_bytes = max(self.peak_bytes, 1024 * message[4])
                else:
                    raise OSError(message[1])
                if not conn.poll():
                    break

    def stop(self) -> None:
        """Let the processes finish what they were sent and exit."""
        for conn in self._conns:
            conn.close()
        for proc in self._procs:
            proc.wait()
        self._release()

    def kill(self) -> None:
        """Stop the processes now (their chunks in memory are lost)."""
        for proc in self._procs:
            proc.kill()
        for conn, proc in zip(self._conns, self._procs, strict=True):
            conn.close()
            proc.wait()
        self._release()

    def _release(self) -> None:
        """Forget the processes (exited), remove staged clip files never used and unmap the shared memory."""
        self._drop_staged()
        self._conns, self._procs = [], []
        if self._ring is not None:
            with contextlib.suppress(BufferError):  # a view still held (an interrupted copy's frame): unmapped later
                self._ring.close()
            self._ring = None
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1


def _close_into(stream: CrateStream, tmp: Path) -> None:
    """Close ``stream`` and move its file to ``tmp``; on failure, remove it and raise a one-line OSError."""
    try:
        stream.close()
        os.replace(stream.path, tmp)
    except OSError as err:
        stream.discard()
        raise OSError(f"{tmp}: USD export failed: {err.strerror or err}") from None


_PACKAGE_ROOT = str(Path(__file__).resolve().parents[2])
_ALLOCATOR = {"MALLOC_MMAP_THRESHOLD_": str(32 << 20), "MALLOC_TRIM_THRESHOLD_": str(1 << 40)}
"""glibc keeps a process's freed chunk arrays for the next chunk instead of returning them to the system:
touching fresh pages again cost more than the export on the machines measured (docs/decisions.md)."""


def _unlinked_file() -> int:
    """A descriptor of a file with no name, where ``memfd_create`` is missing."""
    import tempfile

    with tempfile.TemporaryFile() as f:
        return os.dup(f.fileno())


def _serve(conn: Connection, fd: int) -> None:
    """A writer process's loop: clip files staged ahead, frames into its chunk, chunks exported, until EOF."""
    first = conn.recv()
    while first[0] == "stage":  # before the first frame: the clips' topology and manifest, ahead
        try:
            write_clip_files(Path(first[1]), *first[2:])
        except Exception as err:  # reported to the caller, which stops
            conn.send(("error", f"USD writer process: {err}"))
            return
        conn.send(("staged",))
        first = conn.recv()
    names, prop_paths, ranges = first
    ring = mmap.mmap(fd, os.fstat(fd).st_size)
    floats = 3 * ranges[-1]
    chunk: Chunk | None = None
    busy = 0.0
    while True:
        try:
            message = conn.recv()
        except EOFError:
            return
        clock = time.perf_counter()
        kind, number = message[0], message[1]
        try:
            if kind == "frame":
                frame, slot, matrices, extents = message[2:]
                view = np.frombuffer(ring, np.float32, floats, 4 * floats * slot).reshape(-1, 3)
                chunk = chunk or Chunk(names, prop_paths)
                chunk.add(frame, [view[a:b] for a, b in zip(ranges, ranges[1:], strict=False)], matrices, extents)
                conn.send(("free", slot))
            elif kind == "cut":
                export(chunk.layer, Path(message[2]))
            else:
                chunk.export_single(Path(message[2]), *message[3:])
        except Exception as err:  # reported to the caller, which stops
            conn.send(("error", f"USD writer process: {err}"))
            return
        busy += time.perf_counter() - clock
        if kind in ("cut", "single"):
            conn.send(("done", number, chunk.last, busy, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss))
            chunk, busy = None, 0.0


def main(argv: list[str]) -> int:
    """Serve the caller on the socket and shared memory whose descriptors are ``argv``."""
    try:
        _serve(Connection(int(argv[0])), int(argv[1]))
    except (EOFError, BrokenPipeError, ConnectionResetError):  # the caller is gone
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

"""Animated USD output: one time-sampled ``UsdGeom.Mesh`` per body under ``/World``, streamed in chunks.

A chunk is cut when it holds :data:`CHUNK_BYTES` of samples (:data:`STREAMED_CHUNK_BYTES` where it streams
into a crate on the calling thread) or ``save_every`` seconds after the last cut, whichever comes first, and is
never rewritten:

- a run whose frames all fit in its first chunk writes one self-contained file at the target;
- a longer run streams USD value clips: ``<stem>.clips/`` beside the target holds the topology (written
  once), a manifest and one ``.usdc`` per chunk; the target is a small top-level layer that sublayers the
  topology and lists the clips, replaced atomically after each chunk. Memory stays at a few chunks whatever
  the frame count, and each chunk costs one export of its own bytes.

Large frames' chunks are authored and exported by a few writer processes (:mod:`warpfem.io.usd_workers`),
several at once, while the caller goes on; small frames stream into their chunk's file on the calling thread.
The caller places each chunk, in order, once it is written. Every file is
written to a temporary name and moved into place with ``os.replace``, so each path only ever holds a
complete file. What survives a stop:

- an exception (NaN, a failing kernel), ``KeyboardInterrupt`` (Ctrl-C, or SIGTERM mapped to it by the
  CLI): every frame added, written on leaving the ``with`` block;
- the process killed outright (SIGKILL, power loss): every chunk placed, i.e. every frame up to at most
  ``save_every`` seconds of run time back (plus the chunks being exported), readable through the target.
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import shutil
import signal
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from types import TracebackType

import numpy as np

from warpfem.io.usd_layers import MARKER, Prop, StageInfo, export, extent, moving_paths
from warpfem.io.usd_workers import InlinePool, ProcessPool, default_workers

_FORMATS = {".usdc": "usdc", ".usd": "usdc", ".usda": "usda"}
_NAME_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")

SAVE_EVERY_S = 10.0
"""Default longest time between two chunks on disk (s of wall time)."""

CHUNK_BYTES = 32 << 20
"""Bytes of point samples after which a chunk is cut where writer processes export it (one export of about
this size, held in a process's memory) or where the target is text.

A single file is exported only once its last frame is in, so a run of one chunk waits for its whole export at
the end, which a small chunk keeps short; a longer run's clips are exported while it goes on (the switch point's
measurement: docs/decisions.md)."""

STREAMED_CHUNK_BYTES = 256 << 20
"""Bytes of point samples after which a chunk streamed on the calling thread into a crate is cut: such a chunk
is on disk as it grows and completed in place, so its size costs neither memory nor time at the end, while each
cut costs an export of the top-level layer by usd-core (docs/decisions.md)."""


class UsdWriter:
    """Writes the animated surfaces of several bodies to one ``.usdc`` (or ``.usda``) file or clip set.

    Each body becomes ``/World/<name>``, a ``Mesh`` with its topology (``faceVertexCounts``,
    ``faceVertexIndices``) authored once, ``subdivisionScheme = "none"``, right-handed
    orientation, no normals, and ``points`` and ``extent`` sampled at time code ``frame`` for
    every frame added. Stage metadata: ``upAxis``, ``metersPerUnit = 1``, ``timeCodesPerSecond``
    and ``framesPerSecond`` = fps, ``startTimeCode = 0``, ``endTimeCode`` = the last frame on disk,
    ``defaultPrim = "World"``.

    Used as a context manager it closes on success; on ``KeyboardInterrupt`` it closes too
    (keeping the frames added so far, if any) and re-raises; on any other exception it closes if
    at least one frame was added, else aborts.

    Example::

        with UsdWriter("out.usdc", [("bunny", faces)], fps=60.0) as usd:
            for frame in range(121):
                usd.add_frame(frame, [points])
    """

    def __init__(
        self,
        path: str | Path,
        bodies: Sequence[tuple[str, np.ndarray]],
        fps: float,
        up_axis: str = "Y",
        overwrite: bool = True,
        save_every: float | None = SAVE_EVERY_S,
        chunk_bytes: int | None = None,
        props: Sequence[Prop] = (),
        workers: int | None = None,
        final_frame: int | None = None,
    ):
        """Check the arguments, start the writer processes or stage the clips' topology (nothing visible is written).

        Args:
            path: The output file; its extension picks the format: ``.usdc`` or ``.usd``
                (binary crate) or ``.usda`` (text; its clips are ``.usdc``). Its folder must exist.
            bodies: ``(name, faces)`` per body: a valid, unique USD prim name and an (m, 3)
                integer array of triangle vertex indices.
            fps: Frames per second (> 0); time code = frame number.
            up_axis: ``"Y"`` or ``"Z"``.
            overwrite: Whether an existing file (and clips folder) at ``path`` may be replaced; if not, the
                first write links the file into place, failing if one appeared meanwhile.
            save_every: Longest time between chunks on disk in seconds (0: a chunk per frame); None: chunks
                are cut by size only.
            chunk_bytes: Bytes of point samples per chunk (>= 1); None: :data:`STREAMED_CHUNK_BYTES` for a crate
                target written on the calling thread, else :data:`CHUNK_BYTES`.
            props: Rigid shapes beside the bodies (obstacles, handles): each a :class:`Prop`, written at
                ``/World/<path>`` with its mesh authored once, and its transform too where it is fixed, else
                sampled every frame.
            workers: Writer processes that author and export chunks, several at once (0: on the calling
                thread); None: :func:`~warpfem.io.usd_workers.default_workers` for the bodies' frame size.
            final_frame: The last frame the caller will add, where it knows it: once a run is in clips, the
                top-level layer listing each chunk as the last one to this frame is written ahead as the chunk
                opens, so that closing only moves it into place (the same layer closing would export).

        Raises:
            ValueError: A bad extension, name, face array, fps, up axis, ``save_every``, ``chunk_bytes``, prop or
                worker count.
            FileNotFoundError: The output folder does not exist.
            FileExistsError: ``path`` or its clips folder exists and ``overwrite`` is False.
            OSError: The output folder cannot be written.
        """
        self.path = Path(path)
        _check_arguments(self.path, fps, up_axis, bodies, save_every, chunk_bytes, workers)
        import pxr.Sdf  # noqa: F401  (loaded now, before a run steps, not on its writer's thread at the first chunk)

        self.clips_dir = clips_folder(self.path)
        if not overwrite and (self.path.exists() or self.clips_dir.exists()):
            raise FileExistsError(f"{self.path}: the file exists (overwriting was not asked for)")
        self._tmp = self.path.with_name(f".{self.path.stem}.tmp-{os.getpid()}{self.path.suffix}")
        self._final_top = self.path.with_name(f".{self.path.stem}.tmp-{os.getpid()}-final{self.path.suffix}")
        self._final_frame = final_frame
        self._final_key: tuple | None = None  # the clips and last frame the top-level layer written ahead lists
        self._fps = float(fps)
        self._up_axis = up_axis
        self._bodies: list[tuple[str, np.ndarray]] = []
        self._min_vertices: list[int] = []
        self._vertices: list[int | None] = []
        self._frame_bytes = 0  # a frame's point bytes, once the first frame fixed them
        self._last_frame: int | None = None
        self._frames_added = 0
        self._closed = False
        self._closing = threading.Lock()  # one close at a time: a run's writer thread closes, its caller may too
        self._overwrite = overwrite
        self._save_every = save_every
        self._chunk_limit = chunk_bytes  # None: set once the writer processes are known
        self._saved_at = time.monotonic()
        self._placed = False
        self._clips: list[tuple[int, str]] = []  # placed: (first frame, path relative to the target's folder)
        self._clips_end = 0  # the last frame of the last chunk placed
        self._cut: dict[int, tuple[int, Path]] = {}  # exporting: number -> (first frame, temporary file)
        self._exported: dict[int, int] = {}  # exported, waiting for the chunks before them: number -> last frame
        self._cuts = 0  # chunks cut so far: the open chunk's number
        self._chunk_first: int | None = None  # the open chunk's first frame; None: no chunk open
        self._chunk_bytes = 0
        self._discards: list[threading.Thread] = []  # old clip folders being deleted beside the run
        for name, faces in bodies:
            self._check_body(name, faces)
        self._props = _checked_props(props, {name for name, _ in self._bodies})
        if workers is None:  # the frame's point bytes
            workers = default_workers(12 * sum(self._min_vertices))
        self.workers = workers
        """Writer processes (0: chunks written on the calling thread)."""
        if chunk_bytes is None:
            streamed = not workers and _FORMATS[self.path.suffix.lower()] == "usdc"
            self._chunk_limit = STREAMED_CHUNK_BYTES if streamed else CHUNK_BYTES
        names, prop_paths = [name for name, _ in self._bodies], moving_paths(self._props)
        self._moving = len(prop_paths)
        folder = self.path.parent  # where an inline chunk streams before it is placed
        self._pool = ProcessPool(names, prop_paths, workers) if workers else InlinePool(names, prop_paths, folder)
        staging = self.path.with_name(f".{self.clips_dir.name}.tmp-{os.getpid()}")
        try:
            self._pool.stage_clip_files(staging, self._bodies, self._props)
        except BaseException:
            self._pool.kill()
            raise

    def _check_body(self, name: str, faces: np.ndarray) -> None:
        """Check one body's name and faces and keep them."""
        if not isinstance(name, str) or not _NAME_RE.fullmatch(name):
            raise ValueError(f"body name {name!r} is not a valid USD prim name (letters, digits, underscores)")
        if name in (n for n, _ in self._bodies):
            raise ValueError(f"body name {name!r} is used twice")
        faces = np.asarray(faces)
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0 or not np.issubdtype(faces.dtype, np.integer):
            raise ValueError(
                f"body {name!r}: faces must be a non-empty (m, 3) integer array, got {faces.dtype} {faces.shape}"
            )
        if faces.min() < 0 or faces.max() >= np.iinfo(np.int32).max:
            raise ValueError(f"body {name!r}: face indices must be in 0..2^31-2")
        self._bodies.append((name, np.ascontiguousarray(faces, dtype=np.int32)))
        self._min_vertices.append(int(faces.max()) + 1)
        self._vertices.append(None)

    @property
    def chunks(self) -> int:
        """Chunks on disk as clips so far (0 for a run written as one file)."""
        return len(self._clips)

    @property
    def writer_peak_bytes(self) -> int:
        """The largest peak resident memory of one writer process so far (bytes; 0 with ``workers=0``)."""
        return self._pool.peak_bytes

    @property
    def export_seconds(self) -> float:
        """Time spent authoring and exporting the chunks exported so far, summed over the writer processes (s)."""
        return self._pool.seconds

    @property
    def frames_added(self) -> int:
        """How many frames have been added."""
        return self._frames_added

    def add_frame(
        self,
        frame: int,
        points: Sequence[np.ndarray],
        transforms: Sequence[np.ndarray] = (),
        extents: np.ndarray | None = None,
    ) -> None:
        """Sample every body's points (and extent), and every prop's transform, at time code ``frame``.

        Args:
            frame: The frame number (0: the initial pose); larger than the last one added.
            points: One (n_i, 3) array of finite positions (m) per body, in the order given to the
                constructor; n_i is fixed by the first frame and covers every face index. The arrays are
                copied: the caller may reuse them once this returns.
            transforms: One 4x4 matrix per moving prop (one without a fixed ``matrix``), in the order given to
                the constructor, taking its own frame to the world, for column vectors (``world = matrix @ [x, 1]``).
            extents: Each body's lower and upper corners, (bodies, 2, 3), where the caller has them (the
                simulation reduces them on the device): the points are then not read for them, and a
                non-finite corner stands for non-finite points. None: read off the points.

        Raises:
            ValueError: A frame out of order, a wrong body count or shape, or non-finite points.
            RuntimeError: The writer is closed.
            OSError: Writing a chunk failed (the writer is aborted: the target keeps the chunks placed before).
        """
        if self._closed:
            raise RuntimeError(f"{self.path}: UsdWriter is closed")
        inline = extents is None and not self.workers  # written on this thread: the extents read off the points here
        arrays = self._checked(frame, points, finite=extents is None and not inline)
        if inline:  # a point's NaN or infinity reaches its body's extent: checking that checks the points
            extents = [extent(p) for p in arrays]
        boxes = None if extents is None else self._checked_extents(frame, extents)
        matrices = _checked_transforms(transforms, self._moving) if self._moving or len(transforms) else []
        if threading.current_thread() is threading.main_thread():
            with _held_signals():
                self._add(int(frame), arrays, matrices, boxes)
        else:  # no signal handler runs here: nothing to hold (a frame stream's writer thread, every frame)
            self._add(int(frame), arrays, matrices, boxes)

    def _add(self, frame: int, arrays: list[np.ndarray], matrices: list[np.ndarray], boxes: np.ndarray | None) -> None:
        """Hand a checked frame to the pool and cut a chunk when one is due; a failed write (OSError) aborts."""
        try:
            self._pool.add(self._cuts, frame, arrays, matrices, boxes)
            if self._chunk_first is None:
                self._chunk_first = frame
                self._stage_final_top(frame)
            if self._vertices[0] is None:  # the first frame fixes each body's point count
                self._vertices = [len(p) for p in arrays]
                self._frame_bytes = sum(p.nbytes for p in arrays)
            self._last_frame = frame
            self._frames_added += 1
            self._chunk_bytes += self._frame_bytes
            if self._save_every is not None and time.monotonic() - self._saved_at >= self._save_every:
                self.save()
            elif self._chunk_bytes >= self._chunk_limit:
                self._cut_chunk()
            if self._cut or self.workers:  # chunks on their way, or messages from the writer processes
                self._place_exported(block=False)
        except OSError:
            self.abort()
            raise

    @contextlib.contextmanager
    def _aborting_on_failure(self) -> Iterator[None]:
        """A failed write (OSError) aborts the writer: the target keeps the chunks placed before."""
        try:
            yield
        except OSError:
            self.abort()
            raise

    def _checked(self, frame: int, points: Sequence[np.ndarray], finite: bool = True) -> list[np.ndarray]:
        """``points`` as contiguous float32 arrays, after checking the frame number, shapes and (``finite``) values."""
        if isinstance(frame, bool) or not isinstance(frame, (int, np.integer)) or frame < 0:
            raise ValueError(f"frame must be an integer >= 0, got {frame!r}")
        if self._last_frame is not None and frame <= self._last_frame:
            raise ValueError(f"frame {frame} added after frame {self._last_frame}: frames must increase")
        if len(points) != len(self._bodies):
            raise ValueError(f"expected points for {len(self._bodies)} bodies, got {len(points)}")
        arrays = []
        for i, p in enumerate(points):
            p = np.ascontiguousarray(p, dtype=np.float32)
            name, expected = self._bodies[i][0], self._vertices[i]
            if p.ndim != 2 or p.shape[1] != 3:
                raise ValueError(f"body {name!r}: points must be an (n, 3) array, got shape {p.shape}")
            if expected is None and len(p) < self._min_vertices[i]:
                raise ValueError(f"body {name!r}: {len(p)} points, but its faces use {self._min_vertices[i]} vertices")
            if expected is not None and len(p) != expected:
                raise ValueError(f"body {name!r}: {len(p)} points, expected {expected} (its vertex count)")
            if finite and not np.isfinite(p).all():
                raise ValueError(f"body {name!r}: frame {frame} has non-finite points")
            arrays.append(p)
        return arrays

    def _checked_extents(self, frame: int, extents: np.ndarray) -> np.ndarray:
        """``extents`` as a (bodies, 2, 3) float32 array, after checking its shape and that it is finite."""
        boxes = np.asarray(extents, dtype=np.float32)
        if boxes.shape != (len(self._bodies), 2, 3):
            raise ValueError(f"extents must be a ({len(self._bodies)}, 2, 3) array, got shape {boxes.shape}")
        if not math.isfinite(sum(boxes.ravel().tolist())):  # float32 values summed in float64 cannot overflow
            name = self._bodies[int(np.argmin(np.isfinite(boxes).all(axis=(1, 2))))][0]
            raise ValueError(f"body {name!r}: frame {frame} has non-finite points")
        return boxes

    def save(self) -> None:
        """Cut the frames added since the last chunk as a chunk, and wait until every chunk is on disk.

        Raises:
            RuntimeError: The writer is closed.
            OSError: An export or a move failed (the writer is aborted: temporary files are removed, the
                target keeps the chunks placed before).
            FileExistsError: The first write found a file at the target and ``overwrite`` is False.
        """
        if self._closed:
            raise RuntimeError(f"{self.path}: UsdWriter is closed")
        with _held_signals(), self._aborting_on_failure():
            self._cut_chunk()
            while self._cut:
                self._place_exported(block=True)
        self._saved_at = time.monotonic()

    def _cut_chunk(self) -> None:
        """Hand the open chunk (if any) to be exported as the next clip; it is placed once exported."""
        if self._chunk_first is None:
            return
        if not self._clips and not self._cut:
            self._start_clips()
        name = self.clips_dir / self._clip_name(self._chunk_first)
        tmp = name.with_name(f".{name.stem}.tmp-{os.getpid()}{name.suffix}")
        self._pool.cut(self._cuts, tmp)
        self._cut[self._cuts] = (self._chunk_first, tmp)
        self._cuts += 1
        self._chunk_first, self._chunk_bytes = None, 0
        self._saved_at = time.monotonic()

    def _place_exported(self, block: bool) -> None:
        """Move the exported chunks into place, in order, and list them in the top-level file.

        ``block``: wait for at least one message from the writer processes first.
        """
        self._exported.update(self._pool.done(block and bool(self._cut)))
        while (number := len(self._clips)) in self._exported:
            first, tmp = self._cut.pop(number)
            last = self._exported.pop(number)
            name = tmp.name.replace(f".tmp-{os.getpid()}", "")[1:]
            os.replace(tmp, self.clips_dir / name)
            self._clips.append((first, f"./{self.clips_dir.name}/{name}"))
            self._clips_end = last
            self._write_top()  # after each chunk: the file lists every chunk in place but the last at most

    def _start_clips(self) -> None:
        """Make the clips folder with the topology and the manifest (replacing a folder of ours with ``overwrite``)."""
        folder = self.clips_dir
        if folder.exists() and not (self._overwrite and _is_ours(folder)):
            raise FileExistsError(f"{folder}: the folder exists and is not warpfem clips of this output")
        for leftover in folder.parent.glob(f".{folder.name}.old-*"):  # of a run killed while deleting
            self._discards.append(_discard(leftover))
        if folder.exists():
            self._discards.append(_discard(folder))
        folder.mkdir()
        self._pool.clip_files(folder)

    def _write_top(self) -> None:
        """Replace the top-level layer with one listing the clips placed so far (the one written ahead if it does)."""
        try:
            if self._final_key == (tuple(self._clips), self._clips_end):
                os.replace(self._final_top, self._tmp)
                self._final_key = None
            else:
                export(self._top_layer(self._clips, self._clips_end), self._tmp)
            self._place()
        except BaseException:
            self._tmp.unlink(missing_ok=True)
            raise

    def _stage_final_top(self, first: int) -> None:
        """Write ahead the top-level layer as it will be if the chunk opened at frame ``first`` is the last.

        Only in a run in clips (a chunk cut before), with the final frame (``final_frame``) still to come.
        """
        if self._final_frame is None or first >= self._final_frame or not (self._clips or self._cut):
            return
        cut = [(start, f"./{self.clips_dir.name}/{self._clip_name(start)}") for start, _ in self._cut.values()]
        clips = [*self._clips, *sorted(cut), (first, f"./{self.clips_dir.name}/{self._clip_name(first)}")]
        self._final_key = None
        export(self._top_layer(clips, self._final_frame), self._final_top)
        self._final_key = (tuple(clips), self._final_frame)

    def _top_layer(self, clips: Sequence[tuple[int, str]], end: int) -> object:
        """The top-level layer: metadata to frame ``end``, the topology as a sublayer and ``clips`` (first, path)."""
        from pxr import Sdf, Vt

        top = Sdf.Layer.CreateAnonymous(f"top.{_FORMATS[self.path.suffix.lower()]}")
        top.subLayerPaths.append(f"./{self.clips_dir.name}/topology.usdc")
        world = Sdf.PrimSpec(top, "World", Sdf.SpecifierOver)
        info = {
            "assetPaths": Sdf.AssetPathArray([path for _, path in clips]),
            "primPath": "/World",
            "active": Vt.Vec2dArray([(float(first), float(i)) for i, (first, _) in enumerate(clips)]),
            "manifestAssetPath": Sdf.AssetPath(f"./{self.clips_dir.name}/manifest.usda"),
        }
        world.SetInfo("clips", {"default": info})
        StageInfo(self._up_axis, self._fps).author(top, end)
        return top

    def _clip_name(self, first: int) -> str:
        """The file name of the chunk whose first frame is ``first``."""
        return f"{self.path.stem}.{first:06d}.usdc"

    def _place(self) -> None:
        """Move the exported temporary file onto the target (never over a foreign file without ``overwrite``)."""
        if self._placed or self._overwrite:
            os.replace(self._tmp, self.path)
        else:
            try:
                os.link(self._tmp, self.path)  # atomic, and fails if a file appeared at the target
            except FileExistsError:
                raise FileExistsError(f"{self.path}: the file exists (overwriting was not asked for)") from None
            self._tmp.unlink()
        self._placed = True

    def close(self) -> Path:
        """Write what is left: one self-contained file if no chunk was cut yet, else the last chunk.

        Returns:
            The output path.

        Raises:
            RuntimeError: No frame was added (the writer is aborted) or the writer is closed.
            OSError: An export or a move failed (temporary files are removed; the target keeps the chunks
                written before, if any).
        """
        with self._closing:
            return self._close()

    def _close(self) -> Path:
        """:meth:`close`, with the closing lock held."""
        if self._closed:
            raise RuntimeError(f"{self.path}: UsdWriter is already closed")
        if self._last_frame is None:
            self.abort()
            raise RuntimeError(f"{self.path}: no frame was added; nothing written")
        try:
            with _held_signals():
                if self._clips or self._cut:
                    self.save()
                else:
                    self._write_single()
                self._pool.stop()
                self._final_top.unlink(missing_ok=True)
        except BaseException:
            self.abort()
            raise
        self._closed = True
        self._join_discards()
        return self.path

    def _join_discards(self) -> None:
        """Wait until the old clip folders this run moved aside are deleted (mostly long since, beside the run)."""
        for thread in self._discards:
            thread.join()
        self._discards.clear()

    def _write_single(self) -> None:
        """Write the one chunk there is as a self-contained file, and drop a clips folder of ours left there."""
        self._pool.single(0, self._tmp, self._bodies, self._props, StageInfo(self._up_axis, self._fps))
        while not self._pool.done(block=True):
            pass
        self._place()
        if self._overwrite and self.clips_dir.is_dir() and _is_ours(self.clips_dir):
            self._discards.append(_discard(self.clips_dir))

    def abort(self) -> None:
        """Drop what is in memory and remove temporary files; the target keeps the chunks placed before."""
        self._closed = True
        self._pool.kill()
        self._tmp.unlink(missing_ok=True)
        self._final_top.unlink(missing_ok=True)
        if self.clips_dir.is_dir():
            for leftover in self.clips_dir.glob(f".*.tmp-{os.getpid()}.*"):
                leftover.unlink(missing_ok=True)
        self._join_discards()

    def __enter__(self) -> UsdWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        with self._closing:  # a close under way on another thread finishes first
            if self._closed:
                return
            if exc_type is None or self._last_frame is not None:
                self._close()
            else:
                self.abort()


@contextlib.contextmanager
def _held_signals() -> Iterator[None]:
    """Hold a SIGINT or SIGTERM until the block ends, then deliver it as the handler in place would.

    The writer's bookkeeping and its messages to the writer processes are then never cut halfway by a
    ``KeyboardInterrupt`` (a chunk listed but not sent, a message half read), which left a close waiting
    forever. A second signal inside the block goes to that handler at once, so a writer that cannot finish
    can still be stopped. Outside the main thread (where no signal handler runs) the block runs unchanged.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}

    def hold(signum: int, frame: object) -> None:
        if held:
            _deliver(signum, previous[signum], frame)
        held.append(signum)

    for s in previous:
        signal.signal(s, hold)
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, signal.SIG_DFL if handler is None else handler)
        if held:
            _deliver(held[0], previous[held[0]], None)


def _deliver(signum: int, handler: object, frame: object) -> None:
    """Act on signal ``signum`` as ``handler`` (a function, ``SIG_DFL`` or ``SIG_IGN``) would."""
    if callable(handler):
        handler(signum, frame)
    elif handler in (signal.SIG_DFL, None):
        signal.raise_signal(signum)  # the handler is back in place: the default action (SIGTERM ends the process)


def _check_arguments(
    path: Path,
    fps: float,
    up_axis: str,
    bodies: Sequence[tuple[str, np.ndarray]],
    save_every: float | None,
    chunk_bytes: int | None,
    workers: int | None,
) -> None:
    """Raise on a bad :class:`UsdWriter` argument (the bodies' names and faces are checked one by one after)."""
    suffix = path.suffix.lower()
    if suffix not in _FORMATS:
        raise ValueError(f"{path}: USD output must end in .usdc, .usd or .usda, got '{suffix}'")
    if not path.parent.is_dir():
        raise FileNotFoundError(f"{path}: the output folder {path.parent} does not exist")
    if not (isinstance(fps, (int, float)) and np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a finite number > 0, got {fps!r}")
    if up_axis not in ("Y", "Z"):
        raise ValueError(f'up_axis must be "Y" or "Z", got {up_axis!r}')
    if not bodies:
        raise ValueError("UsdWriter needs at least one body")
    if save_every is not None and not (np.isfinite(save_every) and save_every >= 0):
        raise ValueError(f"save_every must be None or a finite number >= 0, got {save_every!r}")
    if chunk_bytes is not None and (
        isinstance(chunk_bytes, bool) or not isinstance(chunk_bytes, int) or chunk_bytes < 1
    ):
        raise ValueError(f"chunk_bytes must be an integer >= 1, got {chunk_bytes!r}")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 0):
        raise ValueError(f"workers must be an integer >= 0, got {workers!r}")


def clips_folder(path: str | Path) -> Path:
    """The folder beside ``path`` where a long run's chunks go: ``<stem>.clips``."""
    path = Path(path)
    return path.with_name(f"{path.stem}.clips")


def _discard(folder: Path) -> threading.Thread:
    """Move ``folder`` aside under a hidden name beside it and delete it on a thread of its own.

    Deleting an old clip set of gigabytes takes the file system up to a second or more, on the writer's thread
    a stall the run would wait for; moved aside, the new folder is in place at once.
    """
    trash = folder.with_name(f".{folder.name.lstrip('.').split('.old-')[0]}.old-{os.getpid()}-{time.monotonic_ns()}")
    os.rename(folder, trash)
    thread = threading.Thread(
        target=shutil.rmtree, args=(trash,), kwargs={"ignore_errors": True}, name="warpfem-discard"
    )
    thread.start()
    return thread


def _is_ours(folder: Path) -> bool:
    """Whether ``folder`` is a clips folder this writer made (its topology layer carries the marker)."""
    from pxr import Sdf

    topology = folder / "topology.usdc"
    if not topology.is_file():
        return False
    layer = Sdf.Layer.OpenAsAnonymous(str(topology))
    return layer is not None and layer.comment == MARKER


def _checked_props(props: Sequence[Prop], body_names: set[str]) -> list[Prop]:
    """``props`` with float64 vertices and int32 faces, after checking their paths and arrays."""
    checked, seen = [], set()
    for prop in props:
        parts = prop.path.split("/") if isinstance(prop.path, str) else [None]
        if not all(isinstance(part, str) and _NAME_RE.fullmatch(part) for part in parts):
            raise ValueError(f"prop path {prop.path!r} is not a valid USD prim path under /World")
        if prop.path in seen:
            raise ValueError(f"prop path {prop.path!r} is used twice")
        if parts[0] in body_names:
            raise ValueError(f"a body is named '{parts[0]}', which the output uses for the group of {prop.path!r}")
        vertices, faces = np.asarray(prop.vertices, np.float64), np.asarray(prop.faces)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or not np.isfinite(vertices).all():
            raise ValueError(f"prop {prop.path!r}: vertices must be a finite (n, 3) array")
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0 or faces.min() < 0 or faces.max() >= len(vertices):
            raise ValueError(f"prop {prop.path!r}: faces must be a non-empty (m, 3) array of vertex indices")
        matrix = None if prop.matrix is None else _checked_transforms([prop.matrix], 1)[0]
        seen.add(prop.path)
        checked.append(Prop(prop.path, vertices, faces.astype(np.int32), bool(prop.guide), matrix))
    return checked


def _checked_transforms(transforms: Sequence[np.ndarray], count: int) -> list[np.ndarray]:
    """``transforms`` as finite 4x4 float64 matrices, one per moving prop."""
    if len(transforms) != count:
        raise ValueError(f"expected a transform for each of {count} moving props, got {len(transforms)}")
    matrices = [np.asarray(m, np.float64) for m in transforms]
    if any(m.shape != (4, 4) or not np.isfinite(m).all() for m in matrices):
        raise ValueError("prop transforms must be finite 4x4 matrices")
    return matrices

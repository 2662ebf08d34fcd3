"""Animated USD output: one time-sampled ``UsdGeom.Mesh`` per body under ``/World``, streamed in chunks.

A chunk is cut when it holds :data:`CHUNK_BYTES` of samples or ``save_every`` seconds after the last cut,
whichever comes first, and is never rewritten:

- a run whose frames all fit in its first chunk writes one self-contained file at the target;
- a longer run streams USD value clips: ``<stem>.clips/`` beside the target holds the topology (written
  once), a manifest and one ``.usdc`` per chunk; the target is a small top-level layer that sublayers the
  topology and lists the clips, replaced atomically after each chunk.

Each frame's samples go to the open chunk's file as they come (:class:`~warpfem.io.crate.CrateStream`: plain
writes, which let the simulation's threads run meanwhile), and cutting a chunk only adds its index tables,
so memory does not grow with the frame count and nothing is ever rewritten. Every file is written to a
temporary name and moved into place with ``os.replace``, so each path only ever holds a complete file. What
survives a stop:

- an exception (NaN, a failing kernel), ``KeyboardInterrupt`` (Ctrl-C, or SIGTERM mapped to it by the
  CLI): every frame added, written on leaving the ``with`` block;
- the process killed outright (SIGKILL, power loss): every chunk placed, i.e. every frame up to at most
  ``save_every`` seconds of run time back, readable through the target.
"""

from __future__ import annotations

import contextlib
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

from warpfem.io.crate import CrateStream
from warpfem.io.usd_layers import MARKER, Prop, StageInfo, add_topology, export, extent, write_clip_files

_FORMATS = {".usdc": "usdc", ".usd": "usdc", ".usda": "usda"}
_NAME_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")

SAVE_EVERY_S = 10.0
"""Default longest time between two chunks on disk (s of wall time)."""

CHUNK_BYTES = 32 << 20
"""Bytes of point samples after which a chunk is cut.

A run of one chunk is exported as one self-contained file once its last frame is in, which a small chunk keeps
short; a longer run's clips are complete as each is cut (the switch point's measurement: docs/decisions.md)."""


_BODY_ATTRIBUTES = (("points", "point3f[]"), ("extent", "float3[]"))


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
        chunk_bytes: int = CHUNK_BYTES,
        props: Sequence[Prop] = (),
    ):
        """Check the arguments (nothing is written before the first frame).

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
            chunk_bytes: Bytes of point samples per chunk (>= 1).
            props: Rigid shapes moving with the bodies (obstacles, handles): each a :class:`Prop`, written at
                ``/World/<path>`` with its mesh authored once and its transform sampled every frame.

        Raises:
            ValueError: A bad extension, name, face array, fps, up axis, ``save_every``, ``chunk_bytes`` or prop.
            FileNotFoundError: The output folder does not exist.
            FileExistsError: ``path`` or its clips folder exists and ``overwrite`` is False.
        """
        self.path = Path(path)
        suffix = self.path.suffix.lower()
        if suffix not in _FORMATS:
            raise ValueError(f"{self.path}: USD output must end in .usdc, .usd or .usda, got '{suffix}'")
        if not self.path.parent.is_dir():
            raise FileNotFoundError(f"{self.path}: the output folder {self.path.parent} does not exist")
        if not (isinstance(fps, (int, float)) and np.isfinite(fps) and fps > 0):
            raise ValueError(f"fps must be a finite number > 0, got {fps!r}")
        if up_axis not in ("Y", "Z"):
            raise ValueError(f'up_axis must be "Y" or "Z", got {up_axis!r}')
        if not bodies:
            raise ValueError("UsdWriter needs at least one body")
        if save_every is not None and not (np.isfinite(save_every) and save_every >= 0):
            raise ValueError(f"save_every must be None or a finite number >= 0, got {save_every!r}")
        if isinstance(chunk_bytes, bool) or not isinstance(chunk_bytes, int) or chunk_bytes < 1:
            raise ValueError(f"chunk_bytes must be an integer >= 1, got {chunk_bytes!r}")
        import pxr.Sdf  # noqa: F401  (loaded now, before a run steps, not on its writer's thread at the first chunk)
        import pxr.UsdGeom  # noqa: F401

        self.clips_dir = clips_folder(self.path)
        if not overwrite and (self.path.exists() or self.clips_dir.exists()):
            raise FileExistsError(f"{self.path}: the file exists (overwriting was not asked for)")
        self._tmp = self.path.with_name(f".{self.path.stem}.tmp-{os.getpid()}{self.path.suffix}")
        self._fps = float(fps)
        self._up_axis = up_axis
        self._bodies: list[tuple[str, np.ndarray]] = []
        self._min_vertices: list[int] = []
        self._vertices: list[int | None] = []
        self._last_frame: int | None = None
        self._frames_added = 0
        self._closed = False
        self._overwrite = overwrite
        self._save_every = save_every
        self._chunk_limit = chunk_bytes
        self._saved_at = time.monotonic()
        self._placed = False
        self._clips: list[tuple[int, str]] = []  # placed: (first frame, path relative to the target's folder)
        self._clips_end = 0  # the last frame of the last chunk placed
        self._stream: CrateStream | None = None  # the open chunk; None: none open
        self._chunk_first = 0  # the open chunk's first frame
        self._chunk_bytes = 0
        for name, faces in bodies:
            self._check_body(name, faces)
        self._props = _checked_props(props, {name for name, _ in self._bodies})
        self._attributes = [(f"/World/{name}.{a}", t) for name, _ in self._bodies for a, t in _BODY_ATTRIBUTES]
        self._attributes += [(f"/World/{p.path}.xformOp:transform", "matrix4d") for p in self._props]
        self.seconds = 0.0
        """Time spent writing samples and cutting chunks (s)."""

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
    def frames_added(self) -> int:
        """How many frames have been added."""
        return self._frames_added

    def add_frame(self, frame: int, points: Sequence[np.ndarray], transforms: Sequence[np.ndarray] = ()) -> None:
        """Sample every body's points (and extent), and every prop's transform, at time code ``frame``.

        Args:
            frame: The frame number (0: the initial pose); larger than the last one added.
            points: One (n_i, 3) array of finite positions (m) per body, in the order given to the
                constructor; n_i is fixed by the first frame and covers every face index. The arrays are
                copied: the caller may reuse them once this returns.
            transforms: One 4x4 matrix per prop taking its own frame to the world, for column vectors
                (``world = matrix @ [x, 1]``).

        Raises:
            ValueError: A frame out of order, a wrong body count or shape, or non-finite points.
            RuntimeError: The writer is closed.
            OSError: Writing a chunk failed (the writer is aborted: the target keeps the chunks placed before).
        """
        if self._closed:
            raise RuntimeError(f"{self.path}: UsdWriter is closed")
        values = self._checked(frame, points)
        values += [m.T for m in _checked_transforms(transforms, len(self._props))]  # USD: row vectors
        clock = time.perf_counter()
        with _held_signals(), self._aborting_on_failure():
            if self._stream is None:
                self._stream = CrateStream(self._stream_path(int(frame)), self._attributes)
                self._chunk_first = int(frame)
            self._stream.add(float(frame), values)
            for i in range(len(self._bodies)):
                self._vertices[i] = len(values[2 * i])
            self._last_frame = int(frame)
            self._frames_added += 1
            self._chunk_bytes += sum(values[2 * i].nbytes for i in range(len(self._bodies)))
            if self._save_every is not None and time.monotonic() - self._saved_at >= self._save_every:
                self.save()
            elif self._chunk_bytes >= self._chunk_limit:
                self._cut_chunk()
        self.seconds += time.perf_counter() - clock

    def _stream_path(self, first: int) -> Path:
        """Where a chunk starting at frame ``first`` is written, under a temporary name.

        In the clips folder once it exists, else beside the target (the run may still end as one file).
        """
        folder = self.clips_dir if self._clips else self.path.parent
        return folder / f".{self.path.stem}.{first:06d}.tmp-{os.getpid()}.usdc"

    @contextlib.contextmanager
    def _aborting_on_failure(self) -> Iterator[None]:
        """A failed write (OSError) aborts the writer: the target keeps the chunks placed before."""
        try:
            yield
        except OSError:
            self.abort()
            raise

    def _checked(self, frame: int, points: Sequence[np.ndarray]) -> list[np.ndarray]:
        """``points`` as contiguous float32 arrays, each followed by its extent, after checking them.

        The frame number, the shapes and the values are checked: a NaN or an infinity shows in the extent, so one
        pass over the points does both.
        """
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
            box = extent(p)
            if not np.isfinite(box).all():
                raise ValueError(f"body {name!r}: frame {frame} has non-finite points")
            arrays += [p, box]
        return arrays

    def save(self) -> None:
        """Cut the frames added since the last chunk as a chunk: on disk and listed when this returns.

        Raises:
            RuntimeError: The writer is closed.
            OSError: A write or a move failed (the writer is aborted: temporary files are removed, the
                target keeps the chunks placed before).
            FileExistsError: The first write found a file at the target and ``overwrite`` is False.
        """
        if self._closed:
            raise RuntimeError(f"{self.path}: UsdWriter is closed")
        with _held_signals(), self._aborting_on_failure():
            self._cut_chunk()

    def _cut_chunk(self) -> None:
        """Complete the open chunk (if any), move it into the clips folder and list it in the top-level file."""
        self._saved_at = time.monotonic()
        if self._stream is None:
            return
        if not self._clips:
            self._start_clips()
        stream, self._stream, self._chunk_bytes = self._stream, None, 0
        stream.close()
        name = f"{self.path.stem}.{self._chunk_first:06d}.usdc"
        os.replace(stream.path, self.clips_dir / name)
        self._clips.append((self._chunk_first, f"./{self.clips_dir.name}/{name}"))
        self._clips_end = self._last_frame
        self._write_top()

    def _start_clips(self) -> None:
        """Make the clips folder with the topology and the manifest (replacing a folder of ours with ``overwrite``)."""
        folder = self.clips_dir
        if folder.exists():
            if not (self._overwrite and _is_ours(folder)):
                raise FileExistsError(f"{folder}: the folder exists and is not warpfem clips of this output")
            shutil.rmtree(folder)
        folder.mkdir()
        write_clip_files(folder, str(os.getpid()), self._bodies, self._props)

    def _write_top(self) -> None:
        """Replace the top-level layer: metadata, the topology as a sublayer and the clips written so far."""
        from pxr import Sdf, Vt

        top = Sdf.Layer.CreateAnonymous(f"top.{_FORMATS[self.path.suffix.lower()]}")
        top.subLayerPaths.append(f"./{self.clips_dir.name}/topology.usdc")
        world = Sdf.PrimSpec(top, "World", Sdf.SpecifierOver)
        clips = {
            "assetPaths": Sdf.AssetPathArray([path for _, path in self._clips]),
            "primPath": "/World",
            "active": Vt.Vec2dArray([(float(first), float(i)) for i, (first, _) in enumerate(self._clips)]),
            "manifestAssetPath": Sdf.AssetPath(f"./{self.clips_dir.name}/manifest.usda"),
        }
        world.SetInfo("clips", {"default": clips})
        StageInfo(self._up_axis, self._fps).author(top, self._clips_end)
        try:
            export(top, self._tmp)
            self._place()
        except BaseException:
            self._tmp.unlink(missing_ok=True)
            raise

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
        if self._closed:
            raise RuntimeError(f"{self.path}: UsdWriter is already closed")
        if self._last_frame is None:
            self.abort()
            raise RuntimeError(f"{self.path}: no frame was added; nothing written")
        try:
            with _held_signals():
                if self._clips:
                    self._cut_chunk()
                else:
                    self._write_single()
        except BaseException:
            self.abort()
            raise
        self._closed = True
        return self.path

    def _write_single(self) -> None:
        """Write the one chunk there is as a self-contained file, and drop a clips folder of ours left there.

        The chunk's file is completed, opened by usd-core, given the topology and the stage metadata and
        exported to the target's format.
        """
        from pxr import Sdf

        stream, self._stream = self._stream, None
        stream.close()
        layer = Sdf.Layer.OpenAsAnonymous(str(stream.path))
        try:
            if layer is None:
                raise OSError(f"{stream.path}: usd-core could not read the chunk written")
            add_topology(layer, self._bodies, self._props)
            StageInfo(self._up_axis, self._fps).author(layer, self._last_frame)
            export(layer, self._tmp)
        finally:
            stream.path.unlink(missing_ok=True)
        self._place()
        if self._overwrite and self.clips_dir.is_dir() and _is_ours(self.clips_dir):
            shutil.rmtree(self.clips_dir)

    def abort(self) -> None:
        """Drop what is in memory and remove temporary files; the target keeps the chunks placed before."""
        self._closed = True
        if self._stream is not None:
            self._stream.discard()
            self._stream = None
        self._tmp.unlink(missing_ok=True)
        if self.clips_dir.is_dir():
            for leftover in self.clips_dir.glob(f".*.tmp-{os.getpid()}.*"):
                leftover.unlink(missing_ok=True)

    def __enter__(self) -> UsdWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._closed:
            return
        if exc_type is None or self._last_frame is not None:
            self.close()
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


def clips_folder(path: str | Path) -> Path:
    """The folder beside ``path`` where a long run's chunks go: ``<stem>.clips``."""
    path = Path(path)
    return path.with_name(f"{path.stem}.clips")


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
        seen.add(prop.path)
        checked.append(Prop(prop.path, vertices, faces.astype(np.int32), bool(prop.guide)))
    return checked


def _checked_transforms(transforms: Sequence[np.ndarray], count: int) -> list[np.ndarray]:
    """``transforms`` as finite 4x4 float64 matrices, one per prop."""
    if len(transforms) != count:
        raise ValueError(f"expected a transform for each of {count} props, got {len(transforms)}")
    matrices = [np.asarray(m, np.float64) for m in transforms]
    if any(m.shape != (4, 4) or not np.isfinite(m).all() for m in matrices):
        raise ValueError("prop transforms must be finite 4x4 matrices")
    return matrices

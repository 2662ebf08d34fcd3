"""Animated USD output: one time-sampled ``UsdGeom.Mesh`` per body under ``/World``.

The stage is built with the Sdf layer API inside ``Sdf.ChangeBlock`` (about twice as fast as the
Usd API with many prims) in an in-memory layer. Every write (a periodic snapshot, and the final one on
:meth:`UsdWriter.close`) exports the whole layer to a temporary file beside the target and moves it
into place with ``os.replace``, so the target path only ever holds a complete file whose
``endTimeCode`` is its last frame.

What survives a stop:

- an exception (NaN, a failing kernel), ``KeyboardInterrupt`` (Ctrl-C, or SIGTERM mapped to it by the
  CLI): every frame added, written on leaving the ``with`` block;
- the process killed outright (SIGKILL, power loss): the last snapshot, i.e. every frame up to a point
  at most ``max(save_every, export time / SNAPSHOT_OVERHEAD)`` seconds of run time back (plus the frame
  in progress). A snapshot rewrites the whole file, so its interval grows with the file: with the
  default overhead, snapshots take at most about 5 % of the run's wall time.
"""

from __future__ import annotations

import os
import re
import time
from collections.abc import Sequence
from pathlib import Path
from types import TracebackType

import numpy as np

_FORMATS = {".usdc": "usdc", ".usd": "usdc", ".usda": "usda"}
_NAME_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")

SAVE_EVERY_S = 10.0
"""Default shortest time between two snapshots (s of wall time)."""

SNAPSHOT_OVERHEAD = 0.05
"""Largest fraction of wall time spent on snapshots: the next snapshot waits 1 / this times the last export."""


class UsdWriter:
    """Writes the animated surfaces of several bodies to one ``.usdc`` (or ``.usda``) file.

    Each body becomes ``/World/<name>``, a ``Mesh`` with its topology (``faceVertexCounts``,
    ``faceVertexIndices``) authored once, ``subdivisionScheme = "none"``, right-handed
    orientation, no normals, and ``points`` and ``extent`` sampled at time code ``frame`` for
    every frame added. Stage metadata: ``upAxis``, ``metersPerUnit = 1``, ``timeCodesPerSecond``
    and ``framesPerSecond`` = fps, ``startTimeCode = 0``, ``endTimeCode`` = the last frame added,
    ``defaultPrim = "World"``.

    While frames are added the file is saved as a snapshot every ``save_every`` seconds or more
    (see the module docstring), so a killed process leaves the frames up to the last snapshot.

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
    ):
        """Check the arguments and author the topology in an in-memory layer.

        Args:
            path: The output file; its extension picks the format: ``.usdc`` or ``.usd``
                (binary crate) or ``.usda`` (text). Its folder must exist.
            bodies: ``(name, faces)`` per body: a valid, unique USD prim name and an (m, 3)
                integer array of triangle vertex indices.
            fps: Frames per second (> 0); time code = frame number.
            up_axis: ``"Y"`` or ``"Z"``.
            overwrite: Whether an existing file at ``path`` may be replaced; if not, the first write
                links the file into place, failing if one appeared meanwhile.
            save_every: Shortest time between snapshots in seconds (0: after every frame, as long as
                snapshots stay within :data:`SNAPSHOT_OVERHEAD`); None: write only on close.

        Raises:
            ValueError: A bad extension, name, face array, fps, up axis or ``save_every``.
            FileNotFoundError: The output folder does not exist.
            FileExistsError: ``path`` exists and ``overwrite`` is False.
        """
        from pxr import Sdf

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
        if not overwrite and self.path.exists():
            raise FileExistsError(f"{self.path}: the file exists (overwriting was not asked for)")
        self._tmp = self.path.with_name(f".{self.path.stem}.tmp-{os.getpid()}{self.path.suffix}")
        self._fps = float(fps)
        self._up_axis = up_axis
        self._names: list[str] = []
        self._min_vertices: list[int] = []
        self._vertices: list[int | None] = []
        self._last_frame: int | None = None
        self._frames_added = 0
        self._closed = False
        self._overwrite = overwrite
        self._save_every = save_every
        self._saved_at = time.monotonic()
        self._next_gap = save_every
        self._placed = False
        self.snapshots = 0
        self.snapshot_seconds = 0.0

        self._layer = Sdf.Layer.CreateAnonymous(f"warpfem.{_FORMATS[suffix]}")
        with Sdf.ChangeBlock():
            world = Sdf.PrimSpec(self._layer, "World", Sdf.SpecifierDef, "Xform")
            for name, faces in bodies:
                self._add_body(world, name, faces)
        self._points_paths = [Sdf.Path(f"/World/{name}.points") for name in self._names]
        self._extent_paths = [Sdf.Path(f"/World/{name}.extent") for name in self._names]

    def _add_body(self, world: object, name: str, faces: np.ndarray) -> None:
        """Author one body's mesh prim with its topology and empty animated attributes."""
        from pxr import Sdf, Vt

        if not isinstance(name, str) or not _NAME_RE.fullmatch(name):
            raise ValueError(f"body name {name!r} is not a valid USD prim name (letters, digits, underscores)")
        if name in self._names:
            raise ValueError(f"body name {name!r} is used twice")
        faces = np.asarray(faces)
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0 or not np.issubdtype(faces.dtype, np.integer):
            raise ValueError(
                f"body {name!r}: faces must be a non-empty (m, 3) integer array, got {faces.dtype} {faces.shape}"
            )
        if faces.min() < 0 or faces.max() >= np.iinfo(np.int32).max:
            raise ValueError(f"body {name!r}: face indices must be in 0..2^31-2")

        mesh = Sdf.PrimSpec(world, name, Sdf.SpecifierDef, "Mesh")
        counts = Sdf.AttributeSpec(mesh, "faceVertexCounts", Sdf.ValueTypeNames.IntArray)
        counts.default = Vt.IntArray.FromNumpy(np.full(len(faces), 3, dtype=np.int32))
        indices = Sdf.AttributeSpec(mesh, "faceVertexIndices", Sdf.ValueTypeNames.IntArray)
        indices.default = Vt.IntArray.FromNumpy(np.ascontiguousarray(faces, dtype=np.int32).ravel())
        for attr, value in (("subdivisionScheme", "none"), ("orientation", "rightHanded")):
            spec = Sdf.AttributeSpec(mesh, attr, Sdf.ValueTypeNames.Token, Sdf.VariabilityUniform)
            spec.default = value
        Sdf.AttributeSpec(mesh, "points", Sdf.ValueTypeNames.Point3fArray)
        Sdf.AttributeSpec(mesh, "extent", Sdf.ValueTypeNames.Float3Array)
        self._names.append(name)
        self._min_vertices.append(int(faces.max()) + 1)
        self._vertices.append(None)

    @property
    def frames_added(self) -> int:
        """How many frames have been added."""
        return self._frames_added

    def add_frame(self, frame: int, points: Sequence[np.ndarray]) -> None:
        """Sample every body's points (and extent) at time code ``frame``.

        Args:
            frame: The frame number (0: the initial pose); larger than the last one added.
            points: One (n_i, 3) array of finite positions (m) per body, in the order given to the
                constructor; n_i is fixed by the first frame and covers every face index.

        Raises:
            ValueError: A frame out of order, a wrong body count or shape, or non-finite points.
            RuntimeError: The writer is closed.
        """
        from pxr import Sdf, Vt

        if self._closed:
            raise RuntimeError(f"{self.path}: UsdWriter is closed")
        if isinstance(frame, bool) or not isinstance(frame, (int, np.integer)) or frame < 0:
            raise ValueError(f"frame must be an integer >= 0, got {frame!r}")
        if self._last_frame is not None and frame <= self._last_frame:
            raise ValueError(f"frame {frame} added after frame {self._last_frame}: frames must increase")
        if len(points) != len(self._names):
            raise ValueError(f"expected points for {len(self._names)} bodies, got {len(points)}")
        arrays = []
        for i, p in enumerate(points):
            p = np.ascontiguousarray(p, dtype=np.float32)
            name, expected = self._names[i], self._vertices[i]
            if p.ndim != 2 or p.shape[1] != 3:
                raise ValueError(f"body {name!r}: points must be an (n, 3) array, got shape {p.shape}")
            if expected is None and len(p) < self._min_vertices[i]:
                raise ValueError(f"body {name!r}: {len(p)} points, but its faces use {self._min_vertices[i]} vertices")
            if expected is not None and len(p) != expected:
                raise ValueError(f"body {name!r}: {len(p)} points, expected {expected} (its vertex count)")
            if not np.isfinite(p).all():
                raise ValueError(f"body {name!r}: frame {frame} has non-finite points")
            arrays.append(p)

        code = float(frame)
        try:
            with Sdf.ChangeBlock():
                for i, p in enumerate(arrays):
                    extent = np.stack([p.min(axis=0), p.max(axis=0)])
                    self._layer.SetTimeSample(self._points_paths[i], code, Vt.Vec3fArray.FromNumpy(p))
                    self._layer.SetTimeSample(self._extent_paths[i], code, Vt.Vec3fArray.FromNumpy(extent))
        except BaseException:  # e.g. Ctrl-C half way: no body may keep a sample of an unfinished frame
            for path in (*self._points_paths, *self._extent_paths):
                self._layer.EraseTimeSample(path, code)
            raise
        for i, p in enumerate(arrays):
            self._vertices[i] = len(p)
        self._last_frame = int(frame)
        self._frames_added += 1
        if self._next_gap is not None and time.monotonic() - self._saved_at >= self._next_gap:
            self.save()

    def save(self) -> None:
        """Write a snapshot of every frame added so far to the target now (atomically), and go on.

        Raises:
            RuntimeError: No frame was added yet or the writer is closed.
            OSError: The export or the move failed (the temporary file is removed; the target keeps the
                previous snapshot).
            FileExistsError: The first write found a file at the target and ``overwrite`` is False.
        """
        from pxr import UsdGeom

        if self._closed:
            raise RuntimeError(f"{self.path}: UsdWriter is closed")
        if self._last_frame is None:
            raise RuntimeError(f"{self.path}: no frame was added; nothing to save")
        clock = time.monotonic()
        layer = self._layer
        layer.defaultPrim = "World"
        layer.pseudoRoot.SetInfo(UsdGeom.Tokens.upAxis, self._up_axis)
        layer.pseudoRoot.SetInfo(UsdGeom.Tokens.metersPerUnit, 1.0)
        layer.timeCodesPerSecond = self._fps
        layer.framesPerSecond = self._fps
        layer.startTimeCode = 0.0
        layer.endTimeCode = float(self._last_frame)
        try:
            if not layer.Export(str(self._tmp)):
                raise OSError(f"{self.path}: USD export to {self._tmp} failed")
            self._place()
        except BaseException:
            self._tmp.unlink(missing_ok=True)
            raise
        now = time.monotonic()
        self.snapshots += 1
        self.snapshot_seconds += now - clock
        self._saved_at = now
        if self._save_every is not None:
            self._next_gap = max(self._save_every, (now - clock) / SNAPSHOT_OVERHEAD)

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
        """Write the stage and move it into place atomically.

        Returns:
            The output path.

        Raises:
            RuntimeError: No frame was added (the writer is aborted) or the writer is closed.
            OSError: The export or the move failed (the temporary file is removed; the target keeps the
                last snapshot, if any).
        """
        if self._closed:
            raise RuntimeError(f"{self.path}: UsdWriter is already closed")
        if self._last_frame is None:
            self.abort()
            raise RuntimeError(f"{self.path}: no frame was added; nothing written")
        try:
            self.save()
        except BaseException:
            self.abort()
            raise
        self._closed = True
        self._layer = None
        return self.path

    def abort(self) -> None:
        """Drop everything: remove the temporary file if there is one; the target keeps any snapshot."""
        self._closed = True
        self._layer = None
        self._tmp.unlink(missing_ok=True)

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

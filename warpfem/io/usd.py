"""Animated USD output: one time-sampled ``UsdGeom.Mesh`` per body under ``/World``, streamed in chunks.

Frames are gathered in an in-memory layer (built with the Sdf layer API inside ``Sdf.ChangeBlock``, about
twice as fast as the Usd API with many prims). A chunk is cut when it holds :data:`CHUNK_BYTES` of samples
or ``save_every`` seconds after the last cut, whichever comes first, and is never rewritten:

- a run whose frames all fit in its first chunk writes one self-contained file at the target;
- a longer run streams USD value clips: ``<stem>.clips/`` beside the target holds the topology (written
  once), a manifest and one ``.usdc`` per chunk; the target is a small top-level layer that sublayers the
  topology and lists the clips, replaced atomically after each chunk. Memory stays at one chunk whatever
  the frame count, and each chunk costs one export of its own bytes.

Every file is written to a temporary name and moved into place with ``os.replace``, so each path only ever
holds a complete file. What survives a stop:

- an exception (NaN, a failing kernel), ``KeyboardInterrupt`` (Ctrl-C, or SIGTERM mapped to it by the
  CLI): every frame added, written on leaving the ``with`` block;
- the process killed outright (SIGKILL, power loss): every finished chunk, i.e. every frame up to at
  most ``save_every`` seconds of run time back (plus the chunk in progress), readable through the target.
"""

from __future__ import annotations

import ctypes
import functools
import os
import re
import shutil
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

import numpy as np

from warpfem.io.penetration import bounds

_FORMATS = {".usdc": "usdc", ".usd": "usdc", ".usda": "usda"}
_NAME_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_MARKER = "warpfem.clips"  # the topology layer's comment: marks a clips folder as ours to replace

SAVE_EVERY_S = 10.0
"""Default longest time between two chunks on disk (s of wall time)."""

CHUNK_BYTES = 256 << 20
"""Bytes of point samples after which a chunk is cut (one export of about this size)."""


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
        """Check the arguments and author the topology in an in-memory layer.

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
        if isinstance(chunk_bytes, bool) or not isinstance(chunk_bytes, int) or chunk_bytes < 1:
            raise ValueError(f"chunk_bytes must be an integer >= 1, got {chunk_bytes!r}")
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
        self._clips: list[tuple[int, str]] = []  # (first frame, path relative to the target's folder)
        self._chunk: Sdf.Layer | None = None
        self._chunk_first = 0
        self._chunk_bytes = 0
        for name, faces in bodies:
            self._check_body(name, faces)
        self._props = _checked_props(props, {name for name, _ in self._bodies})
        self._transform_paths = [Sdf.Path(f"/World/{p.path}.xformOp:transform") for p in self._props]
        self._points_paths = [Sdf.Path(f"/World/{name}.points") for name, _ in self._bodies]
        self._extent_paths = [Sdf.Path(f"/World/{name}.extent") for name, _ in self._bodies]

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
        """Chunks written as clips so far (0 for a run written as one file)."""
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
            OSError: Writing a chunk failed.
        """
        from pxr import Gf, Sdf, Vt

        if self._closed:
            raise RuntimeError(f"{self.path}: UsdWriter is closed")
        arrays = self._checked(frame, points)
        matrices = _checked_transforms(transforms, len(self._props))
        if self._chunk is None:
            self._chunk = _layer(self._bodies, self._props, topology=False)
            self._chunk_first = int(frame)
        code = float(frame)
        try:
            with Sdf.ChangeBlock():
                for i, p in enumerate(arrays):
                    extent = _extent(p)
                    self._chunk.SetTimeSample(self._points_paths[i], code, _vec3f_array(p))
                    self._chunk.SetTimeSample(self._extent_paths[i], code, Vt.Vec3fArray.FromNumpy(extent))
                for path, m in zip(self._transform_paths, matrices, strict=True):
                    self._chunk.SetTimeSample(path, code, Gf.Matrix4d(m.T.tolist()))
        except BaseException:  # e.g. Ctrl-C half way: nothing may keep a sample of an unfinished frame
            for path in (*self._points_paths, *self._extent_paths, *self._transform_paths):
                self._chunk.EraseTimeSample(path, code)
            raise
        for i, p in enumerate(arrays):
            self._vertices[i] = len(p)
        self._last_frame = int(frame)
        self._frames_added += 1
        self._chunk_bytes += sum(p.nbytes for p in arrays)
        due = self._save_every is not None and time.monotonic() - self._saved_at >= self._save_every
        if self._chunk_bytes >= self._chunk_limit or due:
            self.save()

    def _checked(self, frame: int, points: Sequence[np.ndarray]) -> list[np.ndarray]:
        """``points`` as contiguous float32 arrays, after checking the frame number, shapes and values."""
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
            if not np.isfinite(p).all():
                raise ValueError(f"body {name!r}: frame {frame} has non-finite points")
            arrays.append(p)
        return arrays

    def save(self) -> None:
        """Write the frames added since the last chunk as a chunk now, and go on (nothing if there are none).

        Raises:
            RuntimeError: The writer is closed.
            OSError: An export or a move failed (temporary files are removed; the target keeps the chunks
                written before).
            FileExistsError: The first write found a file at the target and ``overwrite`` is False.
        """
        if self._closed:
            raise RuntimeError(f"{self.path}: UsdWriter is closed")
        if self._chunk is None:
            return
        if not self._clips:
            self._start_clips()
        name = f"{self.path.stem}.{self._chunk_first:06d}.usdc"
        self._export(self._chunk, self.clips_dir / name)
        self._clips.append((self._chunk_first, f"./{self.clips_dir.name}/{name}"))
        self._chunk, self._chunk_bytes = None, 0
        self._write_top()
        self._saved_at = time.monotonic()

    def _start_clips(self) -> None:
        """Make the clips folder with the topology and the manifest (replacing a folder of ours with ``overwrite``)."""
        folder = self.clips_dir
        if folder.exists():
            if not (self._overwrite and _is_ours(folder)):
                raise FileExistsError(f"{folder}: the folder exists and is not warpfem clips of this output")
            shutil.rmtree(folder)
        folder.mkdir()
        topology = _layer(self._bodies, self._props, topology=True)
        topology.comment = _MARKER
        self._export(topology, folder / "topology.usdc")
        self._export(_layer(self._bodies, self._props, topology=False), folder / "manifest.usda")

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
        self._stage_metadata(top)
        self._export(top, self.path, target=True)

    def _stage_metadata(self, layer: object) -> None:
        """Author the stage metadata on ``layer``, its end at the last frame added."""
        from pxr import UsdGeom

        layer.defaultPrim = "World"
        layer.pseudoRoot.SetInfo(UsdGeom.Tokens.upAxis, self._up_axis)
        layer.pseudoRoot.SetInfo(UsdGeom.Tokens.metersPerUnit, 1.0)
        layer.timeCodesPerSecond = self._fps
        layer.framesPerSecond = self._fps
        layer.startTimeCode = 0.0
        layer.endTimeCode = float(self._last_frame)

    def _export(self, layer: object, path: Path, target: bool = False) -> None:
        """Export ``layer`` to ``path`` through a temporary file moved into place (``target``: the output)."""
        tmp = self._tmp if target else path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")
        try:
            if not layer.Export(str(tmp)):
                raise OSError(f"{path}: USD export to {tmp} failed")
            if target:
                self._place()
            else:
                os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
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
            if self._clips:
                self.save()
            else:
                self._write_single()
        except BaseException:
            self.abort()
            raise
        self._closed = True
        self._chunk = None
        return self.path

    def _write_single(self) -> None:
        """Write the one chunk there is as a self-contained file, and drop a clips folder of ours left there."""
        layer = self._chunk
        _add_topology(layer, self._bodies, self._props)
        self._stage_metadata(layer)
        self._export(layer, self.path, target=True)
        if self._overwrite and self.clips_dir.is_dir() and _is_ours(self.clips_dir):
            shutil.rmtree(self.clips_dir)

    def abort(self) -> None:
        """Drop what is in memory and remove temporary files; the target keeps the chunks written before."""
        self._closed = True
        self._chunk = None
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


def _vec3f_array(points: np.ndarray) -> object:
    """A ``Vt.Vec3fArray`` of contiguous (n, 3) float32 ``points``.

    Filled by one copy into a fresh array's storage, which its (read-only) buffer exposes: ``FromNumpy``
    converts element by element, much slower (docs/decisions.md). Where the buffer is not the storage
    (checked once per process), ``FromNumpy``.
    """
    from pxr import Vt

    if not _buffer_is_storage():
        return Vt.Vec3fArray.FromNumpy(points)
    array = Vt.Vec3fArray(len(points))
    ctypes.memmove(np.asarray(array).ctypes.data, points.ctypes.data, points.nbytes)
    return array


@functools.cache
def _buffer_is_storage() -> bool:
    """Whether writing through a fresh ``Vt.Vec3fArray``'s buffer changes its elements (read back one by one)."""
    from pxr import Vt

    probe = np.arange(12, dtype=np.float32).reshape(4, 3)
    array = Vt.Vec3fArray(4)
    view = np.asarray(array)
    if view.shape != (4, 3) or view.dtype != np.float32 or not view.flags.c_contiguous:
        return False
    ctypes.memmove(view.ctypes.data, probe.ctypes.data, probe.nbytes)
    return all(tuple(array[i]) == tuple(probe[i]) for i in range(4))


def _extent(points: np.ndarray) -> np.ndarray:
    """The (2, 3) float32 bounding box of (n, 3) points (:func:`~warpfem.io.penetration.bounds`)."""
    return np.array(bounds(points), np.float32)


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
    return layer is not None and layer.comment == _MARKER


@dataclass(frozen=True)
class Prop:
    """A rigid shape written beside the bodies: ``/World/<path>``, a mesh whose transform is sampled per frame.

    Attributes:
        path: Its prim path under ``/World`` (names joined by ``/``, e.g. ``"obstacles/ramp"``).
        vertices: (n, 3) vertices in its own frame (m).
        faces: (m, 3) triangles, wound outward.
        guide: Whether it is a guide (``purpose = "guide"``: shown in viewers, not rendered), as handles are.
    """

    path: str
    vertices: np.ndarray
    faces: np.ndarray
    guide: bool = False


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


def _layer(bodies: Sequence[tuple[str, np.ndarray]], props: Sequence[Prop], topology: bool) -> object:
    """An anonymous layer with ``/World``, a mesh per body and a prim per prop.

    With ``topology`` the prims are defined meshes with their faces; without, ``over`` specs that declare only
    what is animated: a body's ``points`` and ``extent``, a prop's transform (a chunk, or the clips' manifest).
    """
    from pxr import Sdf

    layer = Sdf.Layer.CreateAnonymous("warpfem.usdc")
    with Sdf.ChangeBlock():
        world = Sdf.PrimSpec(layer, "World", Sdf.SpecifierOver)
        for name, _ in bodies:
            mesh = Sdf.PrimSpec(world, name, Sdf.SpecifierOver)
            Sdf.AttributeSpec(mesh, "points", Sdf.ValueTypeNames.Point3fArray)
            Sdf.AttributeSpec(mesh, "extent", Sdf.ValueTypeNames.Float3Array)
        for prop in props:
            parent = world
            for part in prop.path.split("/"):
                parent = parent.nameChildren.get(part) or Sdf.PrimSpec(parent, part, Sdf.SpecifierOver)
            Sdf.AttributeSpec(parent, "xformOp:transform", Sdf.ValueTypeNames.Matrix4d)
    if topology:
        _add_topology(layer, bodies, props)
    return layer


def _add_topology(layer: object, bodies: Sequence[tuple[str, np.ndarray]], props: Sequence[Prop]) -> None:
    """Turn ``layer``'s ``over`` specs into defined meshes with their topology (a prop's mesh in its own frame)."""
    from pxr import Sdf, Vt

    with Sdf.ChangeBlock():
        world = layer.GetPrimAtPath("/World")
        world.specifier, world.typeName = Sdf.SpecifierDef, "Xform"
        for name, faces in bodies:
            _define_mesh(layer.GetPrimAtPath(f"/World/{name}"), faces)
        for prop in props:
            parts = prop.path.split("/")
            for depth in range(1, len(parts)):
                scope = layer.GetPrimAtPath("/World/" + "/".join(parts[:depth]))
                scope.specifier, scope.typeName = Sdf.SpecifierDef, "Scope"
            mesh = layer.GetPrimAtPath(f"/World/{prop.path}")
            _define_mesh(mesh, prop.faces)
            points = Sdf.AttributeSpec(mesh, "points", Sdf.ValueTypeNames.Point3fArray)
            points.default = Vt.Vec3fArray.FromNumpy(prop.vertices.astype(np.float32))
            extent = Sdf.AttributeSpec(mesh, "extent", Sdf.ValueTypeNames.Float3Array)
            extent.default = Vt.Vec3fArray.FromNumpy(_extent(prop.vertices.astype(np.float32)))
            order = Sdf.AttributeSpec(mesh, "xformOpOrder", Sdf.ValueTypeNames.TokenArray, Sdf.VariabilityUniform)
            order.default = Vt.TokenArray(["xformOp:transform"])
            if prop.guide:
                purpose = Sdf.AttributeSpec(mesh, "purpose", Sdf.ValueTypeNames.Token, Sdf.VariabilityUniform)
                purpose.default = "guide"


def _define_mesh(mesh: object, faces: np.ndarray) -> None:
    """Make the ``over`` spec ``mesh`` a defined ``Mesh`` with the topology of ``faces``."""
    from pxr import Sdf, Vt

    mesh.specifier, mesh.typeName = Sdf.SpecifierDef, "Mesh"
    counts = Sdf.AttributeSpec(mesh, "faceVertexCounts", Sdf.ValueTypeNames.IntArray)
    counts.default = Vt.IntArray.FromNumpy(np.full(len(faces), 3, dtype=np.int32))
    indices = Sdf.AttributeSpec(mesh, "faceVertexIndices", Sdf.ValueTypeNames.IntArray)
    indices.default = Vt.IntArray.FromNumpy(np.ascontiguousarray(faces, dtype=np.int32).ravel())
    for attr, value in (("subdivisionScheme", "none"), ("orientation", "rightHanded")):
        spec = Sdf.AttributeSpec(mesh, attr, Sdf.ValueTypeNames.Token, Sdf.VariabilityUniform)
        spec.default = value

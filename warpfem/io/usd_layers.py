"""The USD layers :class:`~warpfem.io.usd.UsdWriter` writes: a chunk of time samples, the topology, the metadata.

Everything here builds Sdf layers in memory with the Sdf API (inside ``Sdf.ChangeBlock``, about twice as fast
as the Usd API with many prims) and needs only usd-core and NumPy, so a writer process can import it alone.
"""

from __future__ import annotations

import ctypes
import functools
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from warpfem.io.penetration import bounds


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


@dataclass(frozen=True)
class StageInfo:
    """The stage metadata every file carries: its up axis and frames per second."""

    up_axis: str
    fps: float

    def author(self, target: object, end: int) -> None:
        """Author it on ``target``: ``upAxis``, ``metersPerUnit = 1``, time codes from 0 to ``end`` at ``fps``."""
        target.defaultPrim = "World"  # the metadata keys by name, so that pxr.UsdGeom is not imported for them
        target.pseudoRoot.SetInfo("upAxis", self.up_axis)
        target.pseudoRoot.SetInfo("metersPerUnit", 1.0)
        target.timeCodesPerSecond = self.fps
        target.framesPerSecond = self.fps
        target.startTimeCode = 0.0
        target.endTimeCode = float(end)


class Chunk:
    """One chunk's time samples in an in-memory layer: each body's points and extent, each prop's transform.

    Args:
        names: The bodies' prim names under ``/World``.
        prop_paths: The props' prim paths under ``/World``.

    Attributes:
        last: The last frame sampled (-1: none yet).
    """

    def __init__(self, names: Sequence[str], prop_paths: Sequence[str]) -> None:
        from pxr import Sdf

        self.layer = layer(names, prop_paths)
        self._points = [Sdf.Path(f"/World/{name}.points") for name in names]
        self._extents = [Sdf.Path(f"/World/{name}.extent") for name in names]
        self._transforms = [Sdf.Path(f"/World/{path}.xformOp:transform") for path in prop_paths]
        self.last = -1

    def add(
        self,
        frame: int,
        points: Sequence[np.ndarray],
        matrices: Sequence[np.ndarray],
        extents: Sequence[np.ndarray] | None = None,
    ) -> None:
        """Sample contiguous float32 (n_i, 3) ``points`` and 4x4 column-vector ``matrices`` at ``frame``.

        ``extents``: each body's (2, 3) float32 bounds where known (else read off the points).

        Either every sample of the frame is authored or none (an exception half way, Ctrl-C included,
        erases what was set).
        """
        from pxr import Gf, Sdf, Vt

        code = float(frame)
        boxes = [extent(p) for p in points] if extents is None else extents
        try:
            with Sdf.ChangeBlock():
                for i, p in enumerate(points):
                    self.layer.SetTimeSample(self._points[i], code, vec3f_array(p))
                    self.layer.SetTimeSample(self._extents[i], code, Vt.Vec3fArray.FromNumpy(boxes[i]))
                for path, m in zip(self._transforms, matrices, strict=True):
                    self.layer.SetTimeSample(path, code, Gf.Matrix4d(m.T.tolist()))
        except BaseException:
            for path in (*self._points, *self._extents, *self._transforms):
                self.layer.EraseTimeSample(path, code)
            raise
        self.last = frame

    def export_single(
        self, path: Path, bodies: Sequence[tuple[str, np.ndarray]], props: Sequence[Prop], info: StageInfo
    ) -> None:
        """Export the chunk as a self-contained file (:func:`export_single`)."""
        export_single(self.layer, path, bodies, props, info, self.last)


def export_single(
    target: object,
    path: Path,
    bodies: Sequence[tuple[str, np.ndarray]],
    props: Sequence[Prop],
    info: StageInfo,
    end: int,
) -> None:
    """Export the samples layer ``target`` as a self-contained file.

    The topology and the stage metadata (time codes to frame ``end``) are added to it first.
    """
    add_topology(target, bodies, props)
    info.author(target, end)
    export(target, path)


MARKER = "warpfem.clips"
"""The topology layer's comment: marks a clips folder as one a writer made (and may replace)."""


CLIP_FILES = ("topology.usdc", "manifest.usda")
"""The files of a clips folder besides its chunks: the topology (a sublayer of the top-level file) and the manifest."""


def write_clip_files(folder: Path, tag: str, bodies: Sequence[tuple[str, np.ndarray]], props: Sequence[Prop]) -> None:
    """Write a clips folder's topology (``topology.usdc``, marked) and manifest, each moved into place complete.

    ``tag`` names the temporary files (``.topology.tmp-<tag>.usdc``) so that whoever started the write can
    remove them after a failure.
    """
    names, prop_paths = [name for name, _ in bodies], [p.path for p in props]
    topology = layer(names, prop_paths)
    add_topology(topology, bodies, props)
    topology.comment = MARKER
    for content, name in zip((topology, layer(names, prop_paths)), CLIP_FILES, strict=True):
        path = folder / name
        tmp = path.with_name(f".{path.stem}.tmp-{tag}{path.suffix}")
        export(content, tmp)
        os.replace(tmp, path)


def export(layer: object, path: Path) -> None:
    """Export ``layer`` to ``path`` (usd-core picks the format by the extension).

    Raises:
        OSError: The export failed, with usd-core's last reason in one line.
    """
    from pxr import Tf

    try:
        if layer.Export(str(path)):
            return
        reason = "nothing written"
    except Tf.ErrorException as err:
        reason = str(err).strip().splitlines()[-1].rsplit(" : ", 1)[-1].strip("'")
    raise OSError(f"{path}: USD export failed: {reason}")


def complete_single(
    path: Path, bodies: Sequence[tuple[str, np.ndarray]], props: Sequence[Prop], info: StageInfo, end: int
) -> None:
    """Make the crate of samples at ``path`` self-contained in place: :func:`export_single`'s layer, same file.

    usd-core saves a crate to the file it was read from by appending what changed (the topology, the metadata
    and new tables) and keeping the samples where they are, where an export would copy every sample again.

    Raises:
        OSError: The save failed, with usd-core's last reason in one line.
    """
    from pxr import Sdf, Tf

    try:
        target = Sdf.Layer.FindOrOpen(str(path))
        if target is None:
            raise OSError(f"{path}: usd-core could not read the chunk written")
        add_topology(target, bodies, props)
        info.author(target, end)
        if target.Save():
            return
        reason = "nothing written"
    except Tf.ErrorException as err:
        reason = str(err).strip().splitlines()[-1].rsplit(" : ", 1)[-1].strip("'")
    raise OSError(f"{path}: USD export failed: {reason}")


def vec3f_array(points: np.ndarray) -> object:
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


def extent(points: np.ndarray) -> np.ndarray:
    """The (2, 3) float32 bounding box of (n, 3) points (:func:`~warpfem.io.penetration.bounds`)."""
    return np.array(bounds(points), np.float32)


def animated_attributes(names: Sequence[str], prop_paths: Sequence[str]) -> list[tuple[str, str]]:
    """``(attribute path, USD type name)`` of what a run samples every frame, in the order a frame gives it.

    A body's ``points`` and ``extent`` per name, then a prop's transform per prop path, all under ``/World``.
    """
    result = [(f"/World/{n}.{a}", t) for n in names for a, t in (("points", "point3f[]"), ("extent", "float3[]"))]
    return result + [(f"/World/{p}.xformOp:transform", "matrix4d") for p in prop_paths]


def layer(names: Sequence[str], prop_paths: Sequence[str]) -> object:
    """An anonymous layer of ``over`` specs declaring what is animated (a chunk, or the clips' manifest).

    ``/World`` and every :func:`animated_attributes` path under it.
    """
    from pxr import Sdf

    result = Sdf.Layer.CreateAnonymous("warpfem.usdc")
    with Sdf.ChangeBlock():
        world = Sdf.PrimSpec(result, "World", Sdf.SpecifierOver)
        for path, type_name in animated_attributes(names, prop_paths):
            prim, _, attribute = path.removeprefix("/World/").rpartition(".")
            parent = world
            for part in prim.split("/"):
                parent = parent.nameChildren.get(part) or Sdf.PrimSpec(parent, part, Sdf.SpecifierOver)
            Sdf.AttributeSpec(parent, attribute, Sdf.ValueTypeNames.Find(type_name))
    return result


def add_topology(target: object, bodies: Sequence[tuple[str, np.ndarray]], props: Sequence[Prop]) -> None:
    """Turn ``target``'s ``over`` specs into defined meshes with their topology (a prop's mesh in its own frame)."""
    from pxr import Sdf, Vt

    with Sdf.ChangeBlock():
        world = target.GetPrimAtPath("/World")
        world.specifier, world.typeName = Sdf.SpecifierDef, "Xform"
        for name, faces in bodies:
            _define_mesh(target.GetPrimAtPath(f"/World/{name}"), faces)
        for prop in props:
            parts = prop.path.split("/")
            for depth in range(1, len(parts)):
                scope = target.GetPrimAtPath("/World/" + "/".join(parts[:depth]))
                scope.specifier, scope.typeName = Sdf.SpecifierDef, "Scope"
            mesh = target.GetPrimAtPath(f"/World/{prop.path}")
            _define_mesh(mesh, prop.faces)
            points = Sdf.AttributeSpec(mesh, "points", Sdf.ValueTypeNames.Point3fArray)
            points.default = Vt.Vec3fArray.FromNumpy(prop.vertices.astype(np.float32))
            box = Sdf.AttributeSpec(mesh, "extent", Sdf.ValueTypeNames.Float3Array)
            box.default = Vt.Vec3fArray.FromNumpy(extent(prop.vertices.astype(np.float32)))
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

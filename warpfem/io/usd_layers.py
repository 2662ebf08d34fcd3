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
from typing import TYPE_CHECKING

import numpy as np

from warpfem.io.penetration import bounds

if TYPE_CHECKING:
    from warpfem.io.crate import CrateStream


@dataclass(frozen=True)
class Prop:
    """A rigid shape written beside the bodies: ``/World/<path>``, a mesh in its own frame and a transform.

    Attributes:
        path: Its prim path under ``/World`` (names joined by ``/``, e.g. ``"obstacles/ramp"``).
        vertices: (n, 3) vertices in its own frame (m).
        faces: (m, 3) triangles, wound outward.
        guide: Whether it is a guide (``purpose = "guide"``: shown in viewers, not rendered), as handles are.
        matrix: Its fixed transform (4x4, taking its frame to the world for column vectors) where it does not
            move: written once; None: it moves, and its transform is sampled every frame.
    """

    path: str
    vertices: np.ndarray
    faces: np.ndarray
    guide: bool = False
    matrix: np.ndarray | None = None


@dataclass(frozen=True)
class StageInfo:
    """The stage metadata every file carries: its up axis and frames per second."""

    up_axis: str
    fps: float

    def metadata(self, end: int) -> dict[str, str | float]:
        """The layer's metadata fields, tokens as str and doubles as float.

        ``/World`` the default prim, ``upAxis``, ``metersPerUnit = 1``, time codes from 0 to ``end`` at ``fps``.
        """
        return {
            "defaultPrim": "World",
            "upAxis": self.up_axis,
            "metersPerUnit": 1.0,
            "timeCodesPerSecond": float(self.fps),
            "framesPerSecond": float(self.fps),
            "startTimeCode": 0.0,
            "endTimeCode": float(end),
        }

    def author(self, target: object, end: int) -> None:
        """Author :meth:`metadata` on the Sdf layer ``target`` (by key, so that pxr.UsdGeom is not imported)."""
        for name, value in self.metadata(end).items():
            target.pseudoRoot.SetInfo(name, value)


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
    add_topology(target, topology(bodies, props))
    info.author(target, end)
    export(target, path)


MARKER = "warpfem.clips"
"""The topology layer's comment: marks a clips folder as one a writer made (and may replace)."""


CLIP_FILES = ("topology.usdc", "manifest.usda")
"""The files of a clips folder besides its chunks: the topology (a sublayer of the top-level file) and the manifest."""


def write_clip_files(
    folder: Path, tag: str, bodies: Sequence[tuple[str, np.ndarray]], props: Sequence[Prop]
) -> Topology:
    """Write a clips folder's topology (``topology.usdc``, marked) and manifest, each moved into place complete.

    Returns the :func:`topology` written, which a run that stays one file takes for its own.

    ``tag`` names the temporary files (``.topology.tmp-<tag>.usdc``) so that whoever started the write can
    remove them after a failure.
    """
    names, prop_paths = [name for name, _ in bodies], moving_paths(props)
    described = topology(bodies, props)
    layout = layer(names, prop_paths)
    add_topology(layout, described)
    layout.comment = MARKER
    for content, name in zip((layout, layer(names, prop_paths)), CLIP_FILES, strict=True):
        path = folder / name
        tmp = path.with_name(f".{path.stem}.tmp-{tag}{path.suffix}")
        export(content, tmp)
        os.replace(tmp, path)
    return described


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


def complete_stream(stream: CrateStream, described: Topology, info: StageInfo, end: int) -> None:
    """Give a chunk's crate ``stream``, before it closes, what :func:`export_single` adds.

    That is the topology (``described``, as :func:`topology` gives it) and the metadata.
    """
    prims, attributes = described
    for path, type_name in prims:
        stream.define(path, type_name)
    for path, type_name, value, uniform in attributes:
        stream.set_default(path, type_name, value, uniform)
    for name, value in info.metadata(end).items():
        stream.set_metadata(name, value)


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


def moving_paths(props: Sequence[Prop]) -> list[str]:
    """The prim paths of the props whose transform is sampled every frame (no fixed ``matrix``), in order."""
    return [p.path for p in props if p.matrix is None]


def animated_attributes(names: Sequence[str], prop_paths: Sequence[str]) -> list[tuple[str, str]]:
    """``(attribute path, USD type name)`` of what a run samples every frame, in the order a frame gives it.

    A body's ``points`` and ``extent`` per name, then a moving prop's transform per prop path, all under ``/World``.
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


Topology = tuple[list[tuple[str, str]], list[tuple[str, str, object, bool]]]
"""Prims to define, ``(path, type)``, and attributes to add, ``(path, USD type name, default value, uniform)``."""


def topology(bodies: Sequence[tuple[str, np.ndarray]], props: Sequence[Prop]) -> Topology:
    """What turns the ``over`` specs of the samples into defined meshes with their topology.

    Returns ``(prim path, type)`` per prim to define, and ``(attribute path, USD type name, default value,
    uniform)`` per attribute to add: a mesh's faces, a prop's mesh in its own frame and its transform's order.
    """
    prims, attributes = [("/World", "Xform")], []
    for name, faces in bodies:
        prims.append((f"/World/{name}", "Mesh"))
        attributes += _mesh(f"/World/{name}", faces)
    for prop in props:
        parts = prop.path.split("/")
        prims += [("/World/" + "/".join(parts[:depth]), "Scope") for depth in range(1, len(parts))]
        path, vertices = f"/World/{prop.path}", prop.vertices.astype(np.float32)
        prims.append((path, "Mesh"))
        attributes += _mesh(path, prop.faces)
        attributes += [(f"{path}.points", "point3f[]", vertices, False)]
        attributes += [(f"{path}.extent", "float3[]", extent(vertices), False)]
        attributes += [(f"{path}.xformOpOrder", "token[]", ["xformOp:transform"], True)]
        if prop.matrix is not None:  # USD: row vectors
            attributes += [(f"{path}.xformOp:transform", "matrix4d", np.ascontiguousarray(prop.matrix.T), False)]
        attributes += [(f"{path}.purpose", "token", "guide", True)] if prop.guide else []
    return prims, attributes


def _mesh(path: str, faces: np.ndarray) -> list[tuple[str, str, object, bool]]:
    """The attributes of a triangle mesh's topology at prim ``path``."""
    indices = np.ascontiguousarray(faces, dtype=np.int32).ravel()
    return [
        (f"{path}.faceVertexCounts", "int[]", np.full(len(faces), 3, dtype=np.int32), False),
        (f"{path}.faceVertexIndices", "int[]", indices, False),
        (f"{path}.subdivisionScheme", "token", "none", True),
        (f"{path}.orientation", "token", "rightHanded", True),
    ]


def add_topology(target: object, described: Topology) -> None:
    """Author ``described`` (as :func:`topology` gives it) on the Sdf layer ``target``.

    ``target``'s ``over`` specs hold the samples; a still prop's prim, which no sample made, is made here.
    """
    from pxr import Gf, Sdf, Vt

    values = {"int[]": Vt.IntArray.FromNumpy, "point3f[]": Vt.Vec3fArray.FromNumpy, "token[]": Vt.TokenArray}
    values["float3[]"] = values["point3f[]"]
    values["matrix4d"] = lambda m: Gf.Matrix4d(m.tolist())
    prims, attributes = described
    with Sdf.ChangeBlock():
        for path, type_name in prims:
            spec = Sdf.CreatePrimInLayer(target, path)
            spec.specifier, spec.typeName = Sdf.SpecifierDef, type_name
        for path, type_name, value, uniform in attributes:
            prim, _, name = path.rpartition(".")
            variability = Sdf.VariabilityUniform if uniform else Sdf.VariabilityVarying
            spec = Sdf.AttributeSpec(target.GetPrimAtPath(prim), name, Sdf.ValueTypeNames.Find(type_name), variability)
            spec.default = values[type_name](value) if type_name in values else value

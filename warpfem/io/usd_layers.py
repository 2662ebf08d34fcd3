"""The USD layers :class:`~warpfem.io.usd.UsdWriter` writes with usd-core: the topology, the manifest, the metadata.

Built in memory with the Sdf API (inside ``Sdf.ChangeBlock``, about twice as fast as the Usd API with many
prims). The chunks' time samples are streamed by :mod:`warpfem.io.crate` instead.
"""

from __future__ import annotations

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
        from pxr import UsdGeom

        target.defaultPrim = "World"
        target.pseudoRoot.SetInfo(UsdGeom.Tokens.upAxis, self.up_axis)
        target.pseudoRoot.SetInfo(UsdGeom.Tokens.metersPerUnit, 1.0)
        target.timeCodesPerSecond = self.fps
        target.framesPerSecond = self.fps
        target.startTimeCode = 0.0
        target.endTimeCode = float(end)


MARKER = "warpfem.clips"
"""The topology layer's comment: marks a clips folder as one a writer made (and may replace)."""


def write_clip_files(folder: Path, tag: str, bodies: Sequence[tuple[str, np.ndarray]], props: Sequence[Prop]) -> None:
    """Write a clips folder's topology (``topology.usdc``, marked) and manifest, each moved into place complete.

    ``tag`` names the temporary files (``.topology.tmp-<tag>.usdc``) so that whoever started the write can
    remove them after a failure.
    """
    names, prop_paths = [name for name, _ in bodies], [p.path for p in props]
    topology = layer(names, prop_paths)
    add_topology(topology, bodies, props)
    topology.comment = MARKER
    for content, name in ((topology, "topology.usdc"), (layer(names, prop_paths), "manifest.usda")):
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


def extent(points: np.ndarray) -> np.ndarray:
    """The (2, 3) float32 bounding box of (n, 3) points (:func:`~warpfem.io.penetration.bounds`)."""
    return np.array(bounds(points), np.float32)


def layer(names: Sequence[str], prop_paths: Sequence[str]) -> object:
    """An anonymous layer of ``over`` specs declaring what is animated (a chunk, or the clips' manifest).

    ``/World``, a body's ``points`` and ``extent`` per name, a prop's transform per prop path.
    """
    from pxr import Sdf

    result = Sdf.Layer.CreateAnonymous("warpfem.usdc")
    with Sdf.ChangeBlock():
        world = Sdf.PrimSpec(result, "World", Sdf.SpecifierOver)
        for name in names:
            mesh = Sdf.PrimSpec(world, name, Sdf.SpecifierOver)
            Sdf.AttributeSpec(mesh, "points", Sdf.ValueTypeNames.Point3fArray)
            Sdf.AttributeSpec(mesh, "extent", Sdf.ValueTypeNames.Float3Array)
        for path in prop_paths:
            parent = world
            for part in path.split("/"):
                parent = parent.nameChildren.get(part) or Sdf.PrimSpec(parent, part, Sdf.SpecifierOver)
            Sdf.AttributeSpec(parent, "xformOp:transform", Sdf.ValueTypeNames.Matrix4d)
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

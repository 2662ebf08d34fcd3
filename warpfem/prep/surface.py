"""Loading, repairing and validating closed triangle surface meshes.

A surface is read from OBJ, PLY, STL or OFF (through trimesh, without materials or textures) or from
``builtin:bunny`` (the bunny shipped with Warp, read through pxr). Vertices are welded by position,
degenerate and duplicate faces are dropped, unused vertices removed, small holes closed
(:mod:`warpfem.prep.repair`), every shell oriented outward, shells merged or selected, and the surface
optionally Loop subdivided. It must then be closed, edge-manifold and consistently wound, each shell
with a nonzero enclosed volume. Coordinates keep the file's own units (no scaling).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from warpfem.errors import InputError

BUILTIN_BUNNY = "builtin:bunny"
"""Special mesh name: ``warp/examples/assets/bunny.usd`` (6,102 vertices, 12,200 triangles, closed)."""

WELD_TOLERANCE = 1e-9
"""Vertices closer than this fraction of the bounding-box diagonal are welded into one."""

FLAT = 1.0e-6
"""A surface whose vertices' root-mean-square distance from their best-fitting plane is below this fraction
of its bounding-box diagonal is flat: it has no volume."""

SUPPORTED_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".usd", ".usda", ".usdc")

MAX_EXTENT = 1e30
"""Largest accepted bounding-box diagonal, in file units (cubed volumes must stay finite in float64)."""


@dataclass(frozen=True)
class Surface:
    """A closed, manifold, outward-wound triangle mesh.

    Attributes:
        vertices: (n, 3) float64 vertex positions, in the file's units.
        faces: (m, 3) int32 vertex indices, counter-clockwise seen from outside.
        source: Where the mesh came from (file path or ``builtin:bunny``).
        repairs: Human-readable list of what was changed while loading.
        overlapping: Whether merged shells lie inside or cross each other (the body is their union).
    """

    vertices: np.ndarray
    faces: np.ndarray
    source: str
    repairs: tuple[str, ...]
    overlapping: bool = False


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Return the signed volume enclosed by a closed triangle mesh (positive when wound outward).

    Args:
        vertices: (n, 3) positions.
        faces: (m, 3) vertex indices.

    Returns:
        Volume in cubed mesh units (m^3 for a mesh in meters).
    """
    a, b, c = (np.asarray(vertices, dtype=np.float64)[faces[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Return area-weighted unit vertex normals (zero for unreferenced vertices).

    Args:
        vertices: (n, 3) positions.
        faces: (m, 3) vertex indices, outward winding.

    Returns:
        (n, 3) float64 unit normals.
    """
    v = np.asarray(vertices, dtype=np.float64)
    face_n = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])  # 2 * area * n
    normals = np.zeros_like(v)
    for k in range(3):
        np.add.at(normals, faces[:, k], face_n)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)


def topology_defects(faces: np.ndarray) -> str | None:
    """Describe why a triangle mesh is not a closed, manifold, consistently wound surface.

    Args:
        faces: (m, 3) vertex indices.

    Returns:
        ``None`` when every edge is shared by exactly two faces traversing it in opposite directions,
        else a short description ("not closed: 12 boundary edges", ...).
    """
    if len(faces) == 0:
        return "no faces"
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64)
    undirected = np.sort(directed, axis=1)
    _, counts = np.unique(undirected, axis=0, return_counts=True)
    boundary = int(np.sum(counts == 1))
    nonmanifold = int(np.sum(counts > 2))
    if nonmanifold:
        return f"non-manifold: {nonmanifold} edges shared by more than two faces"
    if boundary:
        return f"not closed: {boundary} boundary edges (holes)"
    if len(np.unique(directed, axis=0)) != len(directed):
        return "winding inconsistent: neighbouring faces are oriented in opposite directions"
    return None


def _bunny_path() -> Path:
    """Warp's bunny asset, found beside Warp's package without importing Warp."""
    from importlib.util import find_spec

    return Path(os.path.dirname(find_spec("warp").origin)) / "examples" / "assets" / "bunny.usd"


def source_file(mesh: str | Path) -> Path | None:
    """The one file whose bytes alone decide what :func:`load_surface` makes of ``mesh``, if there is one.

    An OBJ, PLY, STL or OFF file, or Warp's bunny for ``"builtin:bunny"``; None for a USD file (a layer can
    pull in others) or a file that does not exist.
    """
    path = _bunny_path() if str(mesh) == BUILTIN_BUNNY else Path(mesh)
    if str(mesh) != BUILTIN_BUNNY and path.suffix.lower() in USD_SUFFIXES:
        return None
    return path if path.is_file() else None


def _read_usd_bunny() -> tuple[np.ndarray, np.ndarray]:
    from pxr import Usd, UsdGeom

    path = _bunny_path()
    if not path.exists():
        raise InputError(f"{BUILTIN_BUNNY}: Warp's bunny asset is missing at {path}")
    stage = Usd.Stage.Open(str(path))
    meshes = [UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    if len(meshes) != 1:
        raise InputError(f"{BUILTIN_BUNNY}: expected one Mesh in {path}, found {len(meshes)}")
    points = np.asarray(meshes[0].GetPointsAttr().Get(), dtype=np.float64)
    counts = np.asarray(meshes[0].GetFaceVertexCountsAttr().Get(), dtype=np.int64)
    indices = np.asarray(meshes[0].GetFaceVertexIndicesAttr().Get(), dtype=np.int64)
    if len(counts) == 0 or np.any(counts != 3):
        raise InputError(f"{BUILTIN_BUNNY}: expected a triangle mesh in {path}")
    return points, indices.reshape(-1, 3)


USD_SUFFIXES = (".usd", ".usda", ".usdc")


def read_usd_mesh(path: Path, prim: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A ``UsdGeom.Mesh`` of a USD file as points in metres, world frame at time 0, and triangles.

    Polygons are split into fans; the prim's world transform at time 0 and the stage's ``metersPerUnit``
    apply; a left-handed mesh's triangles are turned to the right-handed winding.

    Args:
        path: The USD file.
        prim: The mesh prim's path; None: the file's only mesh.

    Raises:
        InputError: An unreadable stage, a ``prim`` that is not a mesh, no mesh, or several without ``prim``
            (the message lists them), or a mesh without faces.
    """
    from pxr import Tf, Usd, UsdGeom

    try:
        stage = Usd.Stage.Open(str(path))
    except Tf.ErrorException as exc:
        raise InputError(f"{path}: unreadable USD file ({str(exc).strip().splitlines()[-1]})") from None
    meshes = [str(p.GetPath()) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    if prim is not None:
        if prim not in meshes:
            raise InputError(f"{path}: prim {prim} is not a UsdGeom.Mesh here (meshes: {', '.join(meshes) or 'none'})")
        chosen = prim
    elif len(meshes) != 1:
        listed = ", ".join(meshes)
        found = (
            f"{len(meshes)} meshes ({listed}): name one with prim (--prim for prepare)" if meshes else "no UsdGeom.Mesh"
        )
        raise InputError(f"{path}: {found}")
    else:
        chosen = meshes[0]
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath(chosen))
    time = Usd.TimeCode(0)
    points = np.asarray(mesh.GetPointsAttr().Get(time) or [], dtype=np.float64).reshape(-1, 3)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(time) or [], dtype=np.int64)
    indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(time) or [], dtype=np.int64)
    if len(counts) == 0 or counts.min() < 3 or counts.sum() != len(indices):
        raise InputError(f"{path}: {chosen} has no faces, or faces of fewer than 3 vertices")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    fans = [
        np.stack([indices[s0].repeat(n - 2), indices[s0 + 1 : s0 + n - 1], indices[s0 + 2 : s0 + n]], axis=1)
        for s0, n in zip(starts, counts, strict=True)
    ]
    faces = np.concatenate(fans)
    if mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded:
        faces = faces[:, ::-1]
    world = np.asarray(UsdGeom.Xformable(mesh.GetPrim()).ComputeLocalToWorldTransform(time), dtype=np.float64)
    points = (np.c_[points, np.ones(len(points))] @ world)[:, :3] * UsdGeom.GetStageMetersPerUnit(stage)
    return points, faces


def _read_file(path: Path, prim: str | None = None) -> tuple[np.ndarray, np.ndarray]:

    from warpfem.prep.ply_strips import has_strips, read_strip_ply

    if not path.exists():
        raise InputError(f"{path}: mesh file not found")
    if not path.is_file():
        raise InputError(f"{path}: not a file")
    if path.suffix.lower() not in SUPPORTED_SUFFIXES:
        raise InputError(f"{path}: unsupported mesh format (use {', '.join(SUPPORTED_SUFFIXES)})")
    if path.stat().st_size == 0:
        raise InputError(f"{path}: mesh file is empty")
    if path.suffix.lower() in USD_SUFFIXES:
        return read_usd_mesh(path, prim)
    if prim is not None:
        raise InputError(f"{path}: prim is only for USD files")
    try:
        if path.suffix.lower() == ".obj":
            vertices, faces = _read_obj(path)
        elif path.suffix.lower() == ".ply" and has_strips(path):
            vertices, faces = read_strip_ply(path)
        else:
            vertices, faces = _read_trimesh_or_meshio(path)
    except Exception as exc:  # trimesh and meshio raise many exception types for malformed files
        raise InputError(f"{path}: unreadable mesh file ({type(exc).__name__}: {exc})".splitlines()[0]) from exc
    if len(vertices) == 0:
        raise InputError(f"{path}: mesh file has no vertices")
    return vertices, faces.reshape(-1, 3)


PLY_HEADER_BYTES = 1 << 20
"""The most bytes a PLY header may take before its ``end_header`` line."""


def _check_ply_header(path: Path) -> None:
    """Raise ValueError unless the PLY file's header ends (an ``end_header`` line) within its first bytes."""
    with open(path, "rb") as stream:
        head = stream.read(PLY_HEADER_BYTES)
    if not any(line.strip() == b"end_header" for line in head.splitlines()):
        raise ValueError("PLY header has no end_header line (truncated file?)")


def _read_trimesh_or_meshio(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a PLY, STL or OFF through trimesh, or through meshio where trimesh fails or finds no faces.

    meshio's polygons (quads included) are split into fans. When both fail, trimesh's error is raised.
    """
    import trimesh

    if path.suffix.lower() == ".ply":
        _check_ply_header(path)  # meshio, the fallback, loops forever on a header that never ends
    error: Exception | None = None
    vertices, faces = np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
        vertices = np.asarray(getattr(mesh, "vertices", vertices), dtype=np.float64)
        faces = np.asarray(getattr(mesh, "faces", faces), dtype=np.int64)
        if len(faces):
            return vertices, faces
    except Exception as exc:  # meshio may still read it
        error = exc
    try:
        import meshio

        mesh = meshio.read(path)
    except (Exception, SystemExit):  # meshio exits on some formats it cannot read
        if error is not None:
            raise error from None
        return vertices, faces
    polygons = [np.asarray(block.data, dtype=np.int64) for block in mesh.cells if block.dim == 2]
    fans = [
        np.stack([p[:, 0].repeat(p.shape[1] - 2), p[:, 1:-1].reshape(-1), p[:, 2:].reshape(-1)], axis=1)
        for p in polygons
        if p.ndim == 2 and p.shape[1] >= 3
    ]
    if not fans:
        if error is not None:
            raise error
        return vertices, faces
    points = np.zeros((len(mesh.points), 3))
    points[:, : mesh.points.shape[1]] = mesh.points
    return points, np.concatenate(fans)


def read_triangles(path: str | Path, prim: str | None = None) -> tuple[np.ndarray, np.ndarray, bool]:
    """A triangle mesh as it is (a collider's: open or closed), welded and without degenerate faces.

    Returns:
        Vertices (n, 3) float64 in the file's units (a USD file's: metres, its world frame at time 0), triangles
        (m, 3) int32, and whether the mesh is closed (every edge shared by two faces wound oppositely).

    Raises:
        InputError: An unreadable, empty or unsupported file, non-finite coordinates or no triangle with an area.
    """
    path = Path(path)
    vertices, faces = _read_file(path, prim)
    if not np.isfinite(vertices).all():
        raise InputError(f"{path}: mesh has non-finite coordinates")
    if len(faces) == 0 or faces.min() < 0 or faces.max() >= len(vertices):
        raise InputError(f"{path}: mesh has no triangles, or triangles naming missing vertices")
    vertices, faces = _weld(vertices, faces, [])
    faces = _clean_faces(vertices, faces, [])
    if len(faces) == 0:
        raise InputError(f"{path}: mesh has no triangle with an area")
    vertices, faces = _drop_unused(vertices, faces, [])
    return vertices, faces.astype(np.int32), topology_defects(faces) is None


def _read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Read an OBJ's positions and triangles through trimesh's parser, ignoring UVs and materials.

    ``trimesh.load`` would build texture visuals (needing an image library for ``map_Kd``); the parser
    alone returns one entry per object/group, which are concatenated here.
    """
    from trimesh.exchange.obj import load_obj

    with open(path, "rb") as stream:
        parsed = load_obj(stream, skip_materials=True)
    parts = list(parsed["geometry"].values()) if "geometry" in parsed else [parsed]
    vertices, faces, offset = [], [], 0
    for part in parts:
        vertices.append(np.asarray(part["vertices"], dtype=np.float64).reshape(-1, 3))
        faces.append(np.asarray(part.get("faces", np.zeros((0, 3))), dtype=np.int64).reshape(-1, 3) + offset)
        offset += len(vertices[-1])
    if not vertices:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    return np.concatenate(vertices), np.concatenate(faces)


def _weld(vertices: np.ndarray, faces: np.ndarray, repairs: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices within ``WELD_TOLERANCE`` of the diagonal, keeping first-occurrence order."""
    diag = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    step = WELD_TOLERANCE * diag if diag > 0 else 1.0
    keys = np.round((vertices - vertices.min(axis=0)) / step).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)  # unique groups sorted by their first occurrence
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    if len(first) < len(vertices):
        repairs.append(f"welded {len(vertices) - len(first)} duplicate vertices")
    return vertices[first[order]], rank[inverse.reshape(-1)][faces]


def _clean_faces(vertices: np.ndarray, faces: np.ndarray, repairs: list[str]) -> np.ndarray:
    """Drop faces with repeated or collinear corners and faces repeating another's corners."""
    area2 = np.linalg.norm(
        np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]]),
        axis=1,
    )
    keep = area2 > 0.0
    if not np.all(keep):
        repairs.append(f"dropped {int(np.sum(~keep))} degenerate faces")
        faces = faces[keep]
    _, first = np.unique(np.sort(faces, axis=1), axis=0, return_index=True)
    if len(first) < len(faces):
        repairs.append(f"dropped {len(faces) - len(first)} duplicate faces")
        faces = faces[np.sort(first)]
    return faces


def _drop_unused(vertices: np.ndarray, faces: np.ndarray, repairs: list[str]) -> tuple[np.ndarray, np.ndarray]:
    used = np.zeros(len(vertices), dtype=bool)
    used[faces.reshape(-1)] = True
    if np.all(used):
        return vertices, faces
    repairs.append(f"removed {int(np.sum(~used))} unused vertices")
    remap = np.cumsum(used) - 1
    return vertices[used], remap[faces]


def subdivide_surface(surface: Surface, iterations: int) -> Surface:
    """Return ``surface`` refined by ``iterations`` rounds of Loop subdivision (4x the faces each).

    Args:
        surface: A closed, outward-wound surface.
        iterations: Number of Loop subdivision rounds (0 returns ``surface`` unchanged).

    Returns:
        The subdivided surface, with the subdivision noted in ``repairs``.
    """
    if iterations < 0:
        raise InputError(f"{surface.source}: subdivide must be >= 0, got {iterations}")
    if iterations == 0:
        return surface
    import trimesh

    vertices, faces = trimesh.remesh.subdivide_loop(surface.vertices, surface.faces, iterations=iterations)
    return Surface(
        vertices=np.ascontiguousarray(vertices, dtype=np.float64),
        faces=np.ascontiguousarray(faces, dtype=np.int32),
        source=surface.source,
        repairs=(*surface.repairs, f"Loop-subdivided {iterations}x to {len(faces)} faces"),
        overlapping=surface.overlapping,
    )


def _check_raw(name: str, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Raise :class:`InputError` for a mesh as read that no repair can use.

    No faces, non-finite or overflowing coordinates, indices out of range, all vertices at one point or in one plane.
    """
    if len(faces) == 0:
        raise InputError(f"{name}: mesh has no faces")
    if not np.all(np.isfinite(vertices)):
        bad = int(np.sum(~np.all(np.isfinite(vertices), axis=1)))
        raise InputError(f"{name}: {bad} vertices have NaN or Inf coordinates")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise InputError(f"{name}: face indices out of range")
    with np.errstate(over="ignore"):
        diag = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    if not np.isfinite(diag) or diag > MAX_EXTENT:
        raise InputError(f"{name}: coordinates too large (bounding box beyond {MAX_EXTENT:g} units)")
    if diag == 0.0:
        raise InputError(f"{name}: all vertices are at the same position")
    sample = vertices[:: max(1, len(vertices) // 100_000)]
    thinnest = np.linalg.svd(sample - sample.mean(axis=0), compute_uv=False)[-1] / np.sqrt(len(sample))
    if thinnest <= FLAT * diag:
        raise InputError(
            f"{name}: flat surface: all its vertices lie in one plane, so it encloses zero volume (nothing to simulate)"
        )


def load_surface(
    path: str | Path,
    subdivide: int = 0,
    max_hole: float | None = None,
    shells: str | int = "merge",
    prim: str | None = None,
) -> Surface:
    """Load, repair and validate a closed triangle surface.

    Args:
        path: An OBJ, PLY, STL, OFF or USD file, or ``"builtin:bunny"`` for Warp's bunny.
        subdivide: Rounds of Loop subdivision applied after repair (each gives 4x the faces).
        max_hole: Largest hole closed, as its boundary loop's bounding-box diagonal over the mesh's
            (None: :data:`warpfem.prep.repair.MAX_HOLE_FRACTION`; 0 closes none).
        shells: Several shells: ``"merge"`` into one body, keep the ``"largest"``, ``"error"``, or an
            int k to keep the k-th largest (see :func:`warpfem.prep.repair.select_shells`).
        prim: For a USD file, the mesh prim's path (None: its only mesh; see :func:`read_usd_mesh`).

    Returns:
        The repaired surface, every shell oriented so that its signed volume is positive.

    Raises:
        InputError: One line naming the file and the defect (missing, empty, unreadable, no faces,
            NaN/Inf or overflowing coordinates, all vertices coincident, holes over the limit,
            non-manifold edges, inconsistent winding, zero volume, unwanted shells).
    """
    from warpfem.prep.repair import (
        MAX_HOLE_FRACTION,
        close_small_holes,
        orient_consistently,
        select_shells,
        split_non_manifold,
    )

    name = str(path)
    if name == BUILTIN_BUNNY:
        vertices, faces = _read_usd_bunny()
    else:
        vertices, faces = _read_file(Path(path), prim)
    _check_raw(name, vertices, faces)

    repairs: list[str] = []
    vertices, faces = _weld(vertices, faces, repairs)
    faces = _clean_faces(vertices, faces, repairs)
    if len(faces) == 0:
        raise InputError(f"{name}: mesh has no faces with nonzero area")
    vertices, faces = _drop_unused(vertices, faces, repairs)
    vertices, faces = split_non_manifold(vertices, faces, repairs)
    faces = orient_consistently(faces, name, repairs)
    defect = topology_defects(faces)
    if defect is not None and defect.startswith("not closed"):
        limit = MAX_HOLE_FRACTION if max_hole is None else max_hole
        if limit > 0:
            vertices, faces = close_small_holes(vertices, faces, limit, name, repairs)
            defect = topology_defects(faces)
    if defect is not None and defect.startswith("not closed"):
        raise InputError(f"{name}: open surface, it encloses no volume: {defect}")
    if defect is not None:
        raise InputError(f"{name}: {defect}")
    faces, overlapping = select_shells(vertices, faces, shells, name, repairs)
    vertices, faces = _drop_unused(vertices, faces, [])
    surface = Surface(
        vertices=np.ascontiguousarray(vertices, dtype=np.float64),
        faces=np.ascontiguousarray(faces, dtype=np.int32),
        source=name,
        repairs=tuple(repairs),
        overlapping=overlapping,
    )
    return subdivide_surface(surface, subdivide)

"""Tetrahedralization of a closed surface with Netgen, run in a child process under a time limit.

Netgen keeps the input surface as the boundary of the tet mesh: its first n points are the n surface
vertices, unchanged and in their original order (checked on every call), so coarse surface vertex i is
tet vertex i and the surface faces index the tet vertices directly.
"""

from __future__ import annotations

import numpy as np

from warpfem.errors import InputError
from warpfem.prep.surface import signed_volume
from warpfem.prep.worker import last_message, run_in_child

OPTIMIZATION_STEPS = 3
"""Netgen's 3D optimization passes (``optsteps3d``)."""

VOLUME_TOLERANCE = 1e-6
"""Relative tolerance between the summed tet volume and the surface's enclosed volume."""


def tet_signed_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Return det(b-a, c-a, d-a) / 6 for every tet (positive for the orientation warpfem uses).

    Args:
        points: (p, 3) positions.
        tets: (q, 4) corner indices.

    Returns:
        (q,) float64 signed volumes, in cubed mesh units.
    """
    a, b, c, d = (np.asarray(points, dtype=np.float64)[tets[:, k]] for k in range(4))
    return np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) / 6.0


def tetrahedralize(
    V: np.ndarray,
    F: np.ndarray,
    maxh: float,
    timeout_s: float = 120.0,
    name: str = "mesh",
    optsteps: int = OPTIMIZATION_STEPS,
) -> tuple[np.ndarray, np.ndarray]:
    """Fill a closed, outward-wound surface with tetrahedra using Netgen, keeping the surface.

    Args:
        V: (n, 3) surface positions.
        F: (m, 3) surface triangles, outward winding.
        maxh: Largest tet edge length, in mesh units (e.g. m).
        timeout_s: Wall-clock limit for Netgen, in seconds.
        name: Name of the mesh for error messages.
        optsteps: Netgen's 3D optimization passes.

    Returns:
        ``(tet_vertices, tets)``: (p, 3) float64 positions whose first n rows are ``V`` unchanged, and
        (q, 4) int32 tets, all with positive det(b-a, c-a, d-a), whose boundary is exactly ``F``.

    Raises:
        InputError: If Netgen times out, crashes, makes no tets (the surface may self-intersect), or
            returns tets of mixed orientation, a volume differing from the surface's, a moved surface
            point or a boundary differing from the surface.
    """
    vertices = np.ascontiguousarray(V, dtype=np.float64)
    faces = np.ascontiguousarray(F, dtype=np.int32)
    if not maxh > 0:
        raise InputError(f"{name}: maxh must be positive, got {maxh}")
    inputs = {"vertices": vertices, "faces": faces, "maxh": np.float64(maxh), "optsteps": np.int32(optsteps)}
    out, log = run_in_child("netgen", inputs, timeout_s, name, "Netgen")
    points, tets = out["points"], out["tets"]
    if len(tets) == 0:
        raise InputError(f"{name}: Netgen made no tets (the surface may self-intersect): {last_message(log)}")
    if len(points) < len(vertices) or not np.array_equal(points[: len(vertices)], vertices):
        raise InputError(f"{name}: Netgen moved or reordered the surface points")

    volumes = tet_signed_volumes(points, tets)
    if np.all(volumes < 0):
        tets = tets[:, [0, 2, 1, 3]]
        volumes = -volumes
    elif not np.all(volumes > 0):
        raise InputError(
            f"{name}: Netgen's tets have mixed orientation ({int(np.sum(volumes <= 0))} of {len(tets)} not negative)"
        )
    enclosed = signed_volume(vertices, faces)
    if abs(volumes.sum() - enclosed) > VOLUME_TOLERANCE * abs(enclosed):
        raise InputError(
            f"{name}: Netgen's tets fill volume {volumes.sum():.9g}, but the surface encloses {enclosed:.9g}"
        )
    if not _boundary_matches(tets, faces):
        raise InputError(f"{name}: the boundary of Netgen's tet mesh differs from the input surface")
    return np.ascontiguousarray(points), np.ascontiguousarray(tets, dtype=np.int32)


def boundary_faces(tets: np.ndarray) -> np.ndarray:
    """Return the faces used by exactly one tet, wound outward for positively oriented tets.

    Args:
        tets: (q, 4) positively oriented tets.

    Returns:
        (l, 3) int32 boundary triangles.
    """
    # faces opposite corners 3, 2, 1, 0, each counter-clockwise seen from outside a positive tet
    all_faces = np.concatenate([tets[:, [0, 2, 1]], tets[:, [0, 1, 3]], tets[:, [0, 3, 2]], tets[:, [1, 2, 3]]])
    _, first, counts = np.unique(np.sort(all_faces, axis=1), axis=0, return_index=True, return_counts=True)
    return np.ascontiguousarray(all_faces[first[counts == 1]], dtype=np.int32)


def _boundary_matches(tets: np.ndarray, faces: np.ndarray) -> bool:
    """Whether the tets' boundary is exactly ``faces``, with the same winding (up to rotation)."""
    boundary = boundary_faces(tets)
    if len(boundary) != len(faces):
        return False

    def canonical(tris: np.ndarray) -> np.ndarray:
        rolled = np.stack([np.roll(tris, -k, axis=1) for k in range(3)])  # (3, m, 3) rotations
        pick = np.argmin(rolled[:, :, 0], axis=0)  # rotation that puts the smallest index first
        out = rolled[pick, np.arange(len(tris))]
        return out[np.lexsort(out.T[::-1])]

    return bool(np.array_equal(canonical(boundary), canonical(np.asarray(faces))))


def tet_quality(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return each tet's smallest dihedral angle and its radius ratio.

    Args:
        points: (p, 3) positions.
        tets: (q, 4) positively oriented tets.

    Returns:
        ``(min_dihedral, radius_ratio)``: (q,) smallest interior dihedral angle in degrees (70.5 for a
        regular tet, 0 for a flat one) and (q,) 3 * inradius / circumradius (1 for a regular tet, 0 for a
        flat one).
    """
    x = np.asarray(points, dtype=np.float64)[tets]  # (q, 4, 3)
    # face normals, face k opposite corner k, turned away from that corner (outward)
    normals = np.stack(
        [np.cross(x[:, (k + 2) % 4] - x[:, (k + 1) % 4], x[:, (k + 3) % 4] - x[:, (k + 1) % 4]) for k in range(4)],
        axis=1,
    )
    towards = np.einsum("qkj,qkj->qk", normals, x - x[:, [1, 2, 3, 0]])
    normals = np.where((towards > 0)[:, :, None], -normals, normals)
    areas2 = np.linalg.norm(normals, axis=2)  # twice the face areas
    unit = normals / np.maximum(areas2, 1e-300)[:, :, None]
    # the dihedral angle between faces i and j is pi minus the angle between their outward normals
    cosines = np.stack([np.einsum("ij,ij->i", unit[:, i], unit[:, j]) for i in range(4) for j in range(i + 1, 4)], 1)
    dihedral = np.degrees(np.pi - np.arccos(np.clip(cosines, -1.0, 1.0))).min(axis=1)
    volume = np.abs(tet_signed_volumes(points, tets))
    inradius = 3.0 * volume / (0.5 * areas2.sum(axis=1))
    a = x[:, 1:] - x[:, :1]  # (q, 3, 3) edges from corner 0
    rhs = 0.5 * np.einsum("qij,qij->qi", a, a)
    center = np.linalg.solve(a, rhs[:, :, None])[:, :, 0]  # circumcentre relative to corner 0
    circumradius = np.linalg.norm(center, axis=1)
    return dihedral, 3.0 * inradius / np.maximum(circumradius, 1e-300)

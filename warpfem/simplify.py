"""Quadric-error-metric simplification of a closed surface (Garland & Heckbert, through libigl's qslim)."""

from __future__ import annotations

import numpy as np

from warpfem.errors import InputError
from warpfem.surface import signed_volume, topology_defects


def simplify(
    surface_vertices: np.ndarray, surface_faces: np.ndarray, target_faces: int, name: str = "mesh"
) -> tuple[np.ndarray, np.ndarray]:
    """Simplify a closed surface to at most ``target_faces`` triangles with QEM edge collapses.

    Collapses that would make the surface self-intersect are blocked (``block_intersections``), so a
    clean input stays meshable by Netgen.

    Args:
        surface_vertices: (n, 3) positions of a closed, outward-wound surface.
        surface_faces: (m, 3) vertex indices.
        target_faces: Maximum number of triangles of the result.
        name: Name of the mesh for error messages.

    Returns:
        ``(V, F)``: (k, 3) float64 positions and (l, 3) int32 faces, l <= target_faces normally, with every
        vertex referenced (qslim may stop above the target when every remaining collapse is
        blocked). The input itself (as float64/int32 arrays) when it has <= target_faces.

    Raises:
        InputError: If ``target_faces`` is too small, or the result is not closed, manifold or of
            positive volume.
    """
    vertices = np.asarray(surface_vertices, dtype=np.float64)
    faces = np.asarray(surface_faces, dtype=np.int32)
    if target_faces < 4:
        raise InputError(f"{name}: target face count must be at least 4, got {target_faces}")
    if len(faces) <= target_faces:
        return np.ascontiguousarray(vertices), np.ascontiguousarray(faces)

    import igl

    coarse_v, coarse_f, _, _ = igl.qslim(np.asfortranarray(vertices), np.asfortranarray(faces), int(target_faces), True)
    coarse_v = np.asarray(coarse_v, dtype=np.float64)
    coarse_f = np.asarray(coarse_f, dtype=np.int64)
    used = np.zeros(len(coarse_v), dtype=bool)
    used[coarse_f.reshape(-1)] = True
    remap = np.cumsum(used) - 1
    coarse_v, coarse_f = coarse_v[used], remap[coarse_f]

    defect = topology_defects(coarse_f)
    if defect is not None:
        raise InputError(f"{name}: simplified surface ({len(coarse_f)} faces) is {defect}")
    if signed_volume(coarse_v, coarse_f) <= 0.0:
        raise InputError(f"{name}: simplified surface ({len(coarse_f)} faces) has no positive volume")
    return np.ascontiguousarray(coarse_v), np.ascontiguousarray(coarse_f, dtype=np.int32)

"""Quadric-error-metric simplification of a closed surface (Garland & Heckbert, through libigl's qslim).

Both stages here run in a child process under a time limit (:mod:`warpfem.prep.worker`): QEM itself and,
for input that intersects itself, the clean outer surface rebuilt from the generalized winding number.
"""

from __future__ import annotations

import numpy as np

from warpfem.errors import InputError
from warpfem.prep.surface import signed_volume, topology_defects
from warpfem.prep.worker import run_in_child

OUTER_CELLS_PER_SQRT_FACE = 2.0
"""Outer-surface grid resolution: cells along the longest side = this * sqrt(target faces), so marching
cubes makes roughly 10x the target faces for QEM to reduce (cow.obj: 64 cells -> 11,116 faces)."""

OUTER_CELLS_RANGE = (32, 160)
"""Smallest and largest outer-surface grid resolution (cells along the longest side)."""


FIRST_FACES = 200_000
"""Faces a dense surface of more than twice this many is first reduced to (or to 20 times the target, if more)
by a fast QEM that does not block intersections (fast-simplification), before libigl's blocked QEM, whose cost
grows with the faces it starts from: a scan of millions of triangles would outrun the time budget in it, and a
coarse surface of a few thousand faces resolves nothing of the detail lost between (docs/preprocessing.md,
"Large scans")."""


def first_faces(faces: int, target: int) -> int:
    """The faces a fast QEM first reduces a surface of ``faces`` to for a ``target`` (0: none)."""
    first = max(FIRST_FACES, 20 * target)
    return first if faces > 2 * first else 0


def _compact(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop unreferenced vertices."""
    used = np.zeros(len(vertices), dtype=bool)
    used[faces.reshape(-1)] = True
    remap = np.cumsum(used) - 1
    return vertices[used], remap[faces]


def simplify(
    surface_vertices: np.ndarray,
    surface_faces: np.ndarray,
    target_faces: int,
    name: str = "mesh",
    timeout_s: float = 120.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Simplify a closed surface to at most ``target_faces`` triangles with QEM edge collapses.

    Collapses that would make the surface self-intersect are blocked (``block_intersections``), so a
    clean input stays meshable by Netgen. A surface of more than twice :data:`FIRST_FACES` faces is first
    reduced to :func:`first_faces` by a fast QEM without that blocking (a surface that then intersects itself fails
    the checks after and goes to the next rung).

    Args:
        surface_vertices: (n, 3) positions of a closed, outward-wound surface.
        surface_faces: (m, 3) vertex indices.
        target_faces: Maximum number of triangles of the result.
        name: Name of the mesh for error messages.
        timeout_s: Wall-clock limit for QEM, in seconds.

    Returns:
        ``(V, F)``: (k, 3) float64 positions and (l, 3) int32 faces, l <= target_faces normally, with every
        vertex referenced (qslim may stop above the target when every remaining collapse is
        blocked). The input itself (as float64/int32 arrays) when it has <= target_faces.

    Raises:
        InputError: If ``target_faces`` is too small, QEM times out or crashes, or the result is not
            closed, manifold or of positive volume.
    """
    vertices = np.asarray(surface_vertices, dtype=np.float64)
    faces = np.asarray(surface_faces, dtype=np.int32)
    if target_faces < 4:
        raise InputError(f"{name}: target face count must be at least 4, got {target_faces}")
    if len(faces) <= target_faces:
        return np.ascontiguousarray(vertices), np.ascontiguousarray(faces)

    first = np.int64(first_faces(len(faces), target_faces))
    inputs = {"vertices": vertices, "faces": faces, "target": np.int64(target_faces), "first": first}
    out, _ = run_in_child("qslim", inputs, timeout_s, name, "QEM simplification")
    coarse_v, coarse_f = _compact(out["vertices"].astype(np.float64), out["faces"].astype(np.int64))
    defect = topology_defects(coarse_f)
    if defect is not None:
        raise InputError(f"{name}: simplified surface ({len(coarse_f)} faces) is {defect}")
    if signed_volume(coarse_v, coarse_f) <= 0.0:
        raise InputError(f"{name}: simplified surface ({len(coarse_f)} faces) has no positive volume")
    return np.ascontiguousarray(coarse_v), np.ascontiguousarray(coarse_f, dtype=np.int32)


def outer_cells(target_faces: int) -> int:
    """Return the outer-surface grid resolution (cells along the longest side) for a target face count."""
    low, high = OUTER_CELLS_RANGE
    return int(np.clip(round(OUTER_CELLS_PER_SQRT_FACE * np.sqrt(target_faces)), low, high))


def outer_surface(
    vertices: np.ndarray, faces: np.ndarray, cells: int, name: str = "mesh", timeout_s: float = 120.0
) -> tuple[np.ndarray, np.ndarray]:
    """Rebuild a clean closed surface around a self-intersecting (or nested) one.

    The generalized winding number of the input (``igl.fast_winding_number``) is sampled on a grid with
    ``cells`` cells along the longest side and its 1/2 level set extracted by marching cubes
    (``igl.marching_cubes``): the boundary of everything the input encloses, without intersections.

    Args:
        vertices: (n, 3) positions.
        faces: (m, 3) outward triangles.
        cells: Grid resolution.
        name: Name of the mesh for error messages.
        timeout_s: Wall-clock limit, in seconds.

    Returns:
        ``(V, F)``: float64 positions and int32 faces, closed and outward, vertices welded.

    Raises:
        InputError: On a timeout or crash, or if the level set is not a closed manifold.
    """
    inputs = {"vertices": np.asarray(vertices, dtype=np.float64), "faces": np.asarray(faces), "cells": np.int64(cells)}
    out, _ = run_in_child("outer", inputs, timeout_s, name, "outer surface")
    out_v, out_f = out["vertices"], out["faces"].astype(np.int64)
    if len(out_f) == 0:
        raise InputError(f"{name}: the winding-number outer surface at {cells} cells is empty")
    # marching cubes can emit zero-area triangles where the level set passes through grid points
    a, b, c = (out_v[out_f[:, k]] for k in range(3))
    out_f = out_f[np.linalg.norm(np.cross(b - a, c - a), axis=1) > 0]
    out_v, out_f = _compact(out_v, out_f)
    defect = topology_defects(out_f)
    if defect is not None:
        raise InputError(f"{name}: the winding-number outer surface at {cells} cells is {defect}")
    if signed_volume(out_v, out_f) <= 0.0:
        raise InputError(f"{name}: the winding-number outer surface at {cells} cells has no positive volume")
    return np.ascontiguousarray(out_v), np.ascontiguousarray(out_f, dtype=np.int32)


def smallest_angle(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Return the smallest corner angle of any triangle, in degrees (60 for an equilateral mesh)."""
    corners = np.asarray(vertices, dtype=np.float64)[faces]  # (m, 3, 3)
    smallest = np.inf
    for k in range(3):
        u = corners[:, (k + 1) % 3] - corners[:, k]
        w = corners[:, (k + 2) % 3] - corners[:, k]
        angle = np.arctan2(np.linalg.norm(np.cross(u, w), axis=1), np.einsum("ij,ij->i", u, w))
        smallest = min(smallest, float(angle.min()))
    return float(np.degrees(smallest))


def remesh(
    vertices: np.ndarray, faces: np.ndarray, target_faces: int, name: str = "mesh", timeout_s: float = 120.0
) -> tuple[np.ndarray, np.ndarray]:
    """Remesh a closed surface into about ``target_faces`` well-shaped triangles, keeping its sharp edges.

    Netgen's STL surface mesher (in a child process) finds the feature edges (dihedral angle over 30 deg),
    divides them and fills each smooth patch with near-equilateral triangles of the size that gives the
    target count; features it must keep (small holes, short edges) can make it more. A CAD part's needles
    (QEM keeps long thin triangles on flat faces) become triangles on which Netgen's tets are well shaped.

    Args:
        vertices: (n, 3) positions of a closed, outward-wound surface.
        faces: (m, 3) vertex indices.
        target_faces: Number of triangles aimed at.
        name: Name of the mesh for error messages.
        timeout_s: Wall-clock limit, in seconds.

    Returns:
        ``(V, F)``: float64 positions and int32 faces, closed, manifold and outward.

    Raises:
        InputError: On a timeout or crash, or if the result is not a closed manifold of positive volume.
    """
    inputs = {
        "vertices": np.asarray(vertices, dtype=np.float64),
        "faces": np.asarray(faces, dtype=np.int32),
        "target": np.int64(target_faces),
    }
    out, _ = run_in_child("remesh", inputs, timeout_s, name, "surface remeshing")
    out_v, out_f = _compact(out["vertices"], out["faces"].astype(np.int64))
    defect = topology_defects(out_f) if len(out_f) else "empty"
    if defect is not None:
        raise InputError(f"{name}: the remeshed surface ({len(out_f)} faces) is {defect}")
    if signed_volume(out_v, out_f) < 0.0:
        out_f = out_f[:, ::-1]
    if signed_volume(out_v, out_f) <= 0.0:
        raise InputError(f"{name}: the remeshed surface ({len(out_f)} faces) has no volume")
    return np.ascontiguousarray(out_v), np.ascontiguousarray(out_f, dtype=np.int32)

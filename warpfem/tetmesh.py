"""Tetrahedralization of a closed surface with Netgen, run in a child process under a time limit.

Netgen keeps the input surface as the boundary of the tet mesh: its first n points are the n surface
vertices, unchanged and in their original order (checked on every call), so coarse surface vertex i is
tet vertex i and the surface faces index the tet vertices directly.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from warpfem.errors import InputError
from warpfem.surface import signed_volume

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


def _last_message(log: str) -> str:
    """Return the last non-empty line of Netgen's console output (or a placeholder)."""
    lines = [line.strip() for line in log.splitlines() if line.strip()]
    return lines[-1] if lines else "no output"


def _run_netgen(vertices: np.ndarray, faces: np.ndarray, maxh: float, timeout_s: float, name: str):
    """Run the worker in a child process; return (points, tets) in Netgen's numbering."""
    with tempfile.TemporaryDirectory(prefix="warpfem-netgen-") as tmp:
        src, dst = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(src, vertices=vertices, faces=faces, maxh=np.float64(maxh), optsteps=np.int32(OPTIMIZATION_STEPS))
        try:
            proc = subprocess.run(
                [sys.executable, "-m", "warpfem._netgen_worker", str(src), str(dst)],
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
                errors="replace",
                timeout=timeout_s,
                cwd=tmp,
            )
        except subprocess.TimeoutExpired as exc:
            raise InputError(f"{name}: Netgen did not finish within {timeout_s:g} s") from exc
        if proc.returncode < 0:
            sig = signal.Signals(-proc.returncode).name
            raise InputError(f"{name}: Netgen crashed ({sig}); last output: {_last_message(proc.stdout)}")
        if proc.returncode != 0 or not dst.exists():
            raise InputError(f"{name}: Netgen failed (exit {proc.returncode}): {_last_message(proc.stdout)}")
        with np.load(dst, allow_pickle=False) as data:
            return data["points"], data["tets"], proc.stdout


def tetrahedralize(
    V: np.ndarray, F: np.ndarray, maxh: float, timeout_s: float = 120.0, name: str = "mesh"
) -> tuple[np.ndarray, np.ndarray]:
    """Fill a closed, outward-wound surface with tetrahedra using Netgen, keeping the surface.

    Args:
        V: (n, 3) surface positions.
        F: (m, 3) surface triangles, outward winding.
        maxh: Largest tet edge length, in mesh units (e.g. m).
        timeout_s: Wall-clock limit for Netgen, in seconds.
        name: Name of the mesh for error messages.

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
    points, tets, log = _run_netgen(vertices, faces, maxh, timeout_s, name)
    if len(tets) == 0:
        raise InputError(f"{name}: Netgen made no tets (the surface may self-intersect): {_last_message(log)}")
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

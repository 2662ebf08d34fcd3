"""Tet size from the body's thickness, so that thin parts get enough linear tets across not to lock.

Linear tets are too stiff in bending when a thin part is only one or two tets thick (a 10:1 cantilever
with two tets across sags half as far as it should). The size is therefore chosen from the body's
thickness, not its bounding box: the local thickness at a surface vertex is the distance through the body
along its inward normal (a ray cast), a low percentile of those is the body's thickness, and the tets are
sized to put ``across`` of them over it. A tet budget bounds the result, so a body with a few thin features
does not become hundreds of thousands of tets, and the coarse surface gets enough faces for triangles of
that size (Netgen keeps the surface, so the tets at the boundary are as large as its triangles).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from warpfem.errors import InputError
from warpfem.prep.surface import vertex_normals

THICKNESS_SAMPLES = 3000
"""Surface samples at which the local thickness is measured (dense vertices, evenly strided)."""

THICKNESS_PERCENTILE = 10.0
"""The body's thickness is this percentile of the local thicknesses (a low one, so thin parts count, but
not the minimum, which sits in creases and noise)."""

RAY_OFFSET = 1e-5
"""A thickness ray starts this far inside the surface (fraction of the bounding-box diagonal), past
float32 round-off of its own faces."""

TETS_PER_VOLUME = 5.0
"""Netgen fills a volume V with about this many times V / h^3 tets at maximum size h (measured on the
beam and the scans of docs/preprocessing.md); used to keep the result within the tet budget."""

FACES_PER_AREA = 2.3
"""Near-equilateral triangles of edge h cover an area A with about this many times A / h^2 faces."""

DEFAULT_MAX_TETS = 50000
"""The tet budget of :func:`size_from_thickness` where the caller names none."""

SIZING_FORMAT = 1
"""Version of the sizing rule; part of the preprocessing cache key of every body sized by thickness."""

MAX_SIZED_FACES = 3000
"""The most faces sizing asks QEM for: the scans' QEM surfaces at 5,000-6,600 faces (horse.ply,
stanford-bunny.obj) make Netgen slivers on every rung within the time budget, at 3,000 they mesh."""


@dataclass(frozen=True)
class Sizing:
    """The size chosen for one body (lengths in the units of the surface given).

    Attributes:
        thickness: The body's thickness: :data:`THICKNESS_PERCENTILE` of the local thicknesses.
        maxh: Netgen's largest tet edge.
        faces: Target face count of the coarse surface.
        capped: Whether the tet budget, not the thickness, set ``maxh``.
    """

    thickness: float
    maxh: float
    faces: int
    capped: bool


def local_thickness(vertices: np.ndarray, faces: np.ndarray, samples: int = THICKNESS_SAMPLES) -> np.ndarray:
    """Distance through the body along the inward vertex normal, at up to ``samples`` vertices of a closed surface.

    A Warp ``wp.Mesh`` ray cast on the CPU device (one ray per vertex, started just inside the surface).

    Args:
        vertices: (n, 3) positions of a closed, outward-wound surface.
        faces: (m, 3) triangles.
        samples: Vertices measured (every k-th, for k = ceil(n / samples)).

    Returns:
        (s,) float64 distances to the surface's other side, in the surface's units (rays that leave
        through a hole in a broken surface are left out).
    """
    import warp as wp

    from warpfem.kernels import thickness as K

    v = np.asarray(vertices, dtype=np.float64)
    used = np.unique(faces)
    picked = used[:: max(1, -(-len(used) // samples))]
    centre = 0.5 * (v.max(axis=0) + v.min(axis=0))  # queries in float32 near the origin
    diag = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    with wp.ScopedDevice("cpu"):
        mesh = wp.Mesh(
            points=wp.array(v - centre, dtype=wp.vec3),
            indices=wp.array(np.asarray(faces, dtype=np.int32).reshape(-1), dtype=wp.int32),
        )
        out = wp.empty(len(picked), dtype=float)
        inward = -vertex_normals(v, faces)[picked]
        starts = wp.array(v[picked] - centre, dtype=wp.vec3)
        directions = wp.array(inward, dtype=wp.vec3)
        inputs = [starts, directions, mesh.id, RAY_OFFSET * diag, 2.0 * diag]
        wp.launch(K.inward_ray, dim=len(picked), inputs=inputs, outputs=[out])
        found = out.numpy().astype(np.float64)
    return found[found > 0.0]


def size_from_thickness(
    vertices: np.ndarray,
    faces: np.ndarray,
    across: float,
    max_tets: int,
    min_faces: int,
    max_h: float,
) -> Sizing:
    """Netgen's size and the coarse face count that put ``across`` tets over the body's thickness.

    Args:
        vertices: (n, 3) positions of the closed, outward-wound dense surface.
        faces: (m, 3) its triangles.
        across: Tets over the body's thickness (> 0).
        max_tets: Tet budget: the size is raised until about this many fill the volume (> 0).
        min_faces: Fewest coarse faces (the shape's own budget; sizing only adds faces).
        max_h: Largest tet edge allowed whatever the thickness (surface units).

    Returns:
        The sizing; ``maxh`` is at most ``max_h``, ``faces`` at least ``min_faces``.

    Raises:
        InputError: ``across`` or ``max_tets`` is not positive.
    """
    if not across > 0 or not max_tets > 0:
        raise InputError(f"tets across and the tet budget must be positive, got {across} and {max_tets}")
    v = np.asarray(vertices, dtype=np.float64)
    found = local_thickness(v, faces)
    # no ray found the far side only on a surface with holes (repair closes them first): size by the box
    thickness = float(np.percentile(found, THICKNESS_PERCENTILE)) if len(found) else float(np.linalg.norm(np.ptp(v, 0)))
    a, b, c = (v[faces[:, k]] for k in range(3))
    volume = abs(float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum()) / 6.0)
    area = 0.5 * float(np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())
    budget_h = (TETS_PER_VOLUME * volume / max_tets) ** (1.0 / 3.0)
    h = min(max(thickness / across, budget_h), max_h)
    wanted = round(FACES_PER_AREA * area / h**2)
    faces_sized = int(np.clip(wanted, min_faces, max(min_faces, MAX_SIZED_FACES)))
    return Sizing(thickness, h, faces_sized, budget_h > thickness / across)

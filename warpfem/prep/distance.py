"""Distance field stored at the tet vertices (Kondo & Kanai step 4, after Fisher & Lin 2001).

Every tet vertex gets its signed depth below the dense (visible) surface, negative for the vertices of the
coarse cage that lie outside it, and the unit gradient of that distance, pointing out of the body.
Collision response interpolates both with the barycentric coordinates of a penetrating point, so a
contact starts where the visible surfaces meet.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from warpfem.kernels import distance as K
from warpfem.prep.surface import vertex_normals

ON_SURFACE = 1e-6
"""A vertex closer to the surface than this fraction of the bounding-box diagonal counts as on it.

Warp's mesh queries run in float32 (relative precision ~1e-7), so this is the tightest safe threshold.
"""


def distance_field(
    tet_vertices: np.ndarray, surface_vertices: np.ndarray, surface_faces: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Return the signed depth and outward unit gradient of the distance to the surface at every tet vertex.

    Computed by a Warp kernel over ``wp.Mesh`` closest-point and winding-number queries on the CPU device.

    Args:
        tet_vertices: (p, 3) positions, in mesh units.
        surface_vertices: (n, 3) positions of the closed, outward-wound surface.
        surface_faces: (m, 3) triangles of the surface.

    Returns:
        ``(depth, grad)``: (p,) float64 distances in mesh units, positive inside, negative outside, 0 on the
        surface; and (p, 3) float64 unit vectors out of the body: along the line to the closest surface
        point, or the area-weighted vertex normal (interpolated at the closest point) on the surface.
    """
    x = np.asarray(tet_vertices, dtype=np.float64)
    sv = np.asarray(surface_vertices, dtype=np.float64)
    faces = np.asarray(surface_faces, dtype=np.int32)
    diag = float(np.linalg.norm(sv.max(axis=0) - sv.min(axis=0)))
    with wp.ScopedDevice("cpu"):
        indices = wp.array(faces.reshape(-1), dtype=wp.int32)
        mesh = wp.Mesh(points=wp.array(sv, dtype=wp.vec3), indices=indices, support_winding_number=True)
        depth = wp.empty(len(x), dtype=float)
        grad = wp.empty(len(x), dtype=wp.vec3)
        wp.launch(
            K.surface_distance,
            dim=len(x),
            inputs=[
                wp.array(x, dtype=wp.vec3),
                mesh.id,
                indices,
                wp.array(vertex_normals(sv, faces), dtype=wp.vec3),
                1e30,
                ON_SURFACE * diag,
            ],
            outputs=[depth, grad],
        )
        depth_np = depth.numpy().astype(np.float64)
        grad_np = grad.numpy().astype(np.float64)
    if np.any(depth_np < -1e29):
        raise ValueError("distance query found no surface face for some tet vertices")
    grad_np /= np.linalg.norm(grad_np, axis=1, keepdims=True)
    return depth_np, grad_np


HAUSDORFF_SAMPLES = 20000
"""Random area-weighted samples per surface for :func:`hausdorff` (on top of every vertex)."""


def surface_samples(vertices: np.ndarray, faces: np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    """Return the vertices plus ``count`` area-weighted uniform random points on a triangle surface.

    Args:
        vertices: (n, 3) positions.
        faces: (m, 3) triangles.
        count: Number of random points.
        seed: Random seed (the same seed gives the same points).

    Returns:
        (n + count, 3) float64 points.
    """
    v = np.asarray(vertices, dtype=np.float64)
    a, b, c = (v[faces[:, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(faces), size=count, p=area / area.sum())
    r1, r2 = rng.random((2, count, 1))
    s = np.sqrt(r1)
    return np.concatenate([v, (1.0 - s) * a[pick] + s * (1.0 - r2) * b[pick] + s * r2 * c[pick]])


def distances_to_surface(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Return the distance from each point to a triangle surface (Warp ``wp.Mesh`` queries, CPU device).

    Args:
        points: (k, 3) positions.
        vertices: (n, 3) surface positions.
        faces: (m, 3) surface triangles.

    Returns:
        (k,) float64 distances, in mesh units (float32 precision relative to the extent).
    """
    v = np.asarray(vertices, dtype=np.float64)
    center = 0.5 * (v.max(axis=0) + v.min(axis=0))  # queries in float32 near the origin
    with wp.ScopedDevice("cpu"):
        mesh = wp.Mesh(
            points=wp.array(v - center, dtype=wp.vec3),
            indices=wp.array(np.asarray(faces, dtype=np.int32).reshape(-1), dtype=wp.int32),
        )
        out = wp.empty(len(points), dtype=float)
        query = wp.array(np.asarray(points, dtype=np.float64) - center, dtype=wp.vec3)
        wp.launch(K.unsigned_distance, dim=len(points), inputs=[query, mesh.id, 1e30], outputs=[out])
        return out.numpy().astype(np.float64)


def hausdorff(
    vertices_a: np.ndarray,
    faces_a: np.ndarray,
    vertices_b: np.ndarray,
    faces_b: np.ndarray,
    samples: int = HAUSDORFF_SAMPLES,
) -> tuple[float, float]:
    """Two-sided, sample-based Hausdorff distance between two triangle surfaces.

    Every vertex and ``samples`` random area-weighted points of each surface are measured against the
    other surface; the result is a lower bound of the exact distance that converges as samples grow.

    Args:
        vertices_a: (n, 3) positions of surface A.
        faces_a: (m, 3) triangles of A.
        vertices_b: (k, 3) positions of surface B.
        faces_b: (l, 3) triangles of B.
        samples: Random points per surface.

    Returns:
        ``(a_to_b, b_to_a)``: the largest distance from a sample of A to B and from B to A (mesh units).
    """
    ab = distances_to_surface(surface_samples(vertices_a, faces_a, samples), vertices_b, faces_b)
    ba = distances_to_surface(surface_samples(vertices_b, faces_b, samples, seed=1), vertices_a, faces_a)
    return float(ab.max()), float(ba.max())

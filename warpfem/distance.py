"""Distance field stored at the tet vertices (Kondo & Kanai step 4, after Fisher & Lin 2001).

Every tet vertex gets its unsigned distance to the coarse surface (its depth inside the body) and the
unit gradient of that distance, pointing out of the body. Collision response interpolates both with the
barycentric coordinates of a penetrating vertex.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from warpfem.kernels import distance as K
from warpfem.surface import vertex_normals

ON_SURFACE = 1e-6
"""A vertex closer to the surface than this fraction of the bounding-box diagonal counts as on it.

Warp's mesh queries run in float32 (relative precision ~1e-7), so this is the tightest safe threshold.
"""


def distance_field(
    tet_vertices: np.ndarray, surface_vertices: np.ndarray, surface_faces: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Return the depth and outward unit gradient of the distance to the surface at every tet vertex.

    Computed by a Warp kernel over ``wp.Mesh`` closest-point queries on the CPU device.

    Args:
        tet_vertices: (p, 3) positions (inside or on the surface), in mesh units.
        surface_vertices: (n, 3) positions of the closed, outward-wound surface.
        surface_faces: (m, 3) triangles of the surface.

    Returns:
        ``(depth, grad)``: (p,) float64 unsigned distances in mesh units (0 on the surface) and (p, 3)
        float64 unit vectors: towards the closest surface point for interior vertices, the area-weighted
        vertex normal (interpolated at the closest point) for vertices on the surface.
    """
    x = np.asarray(tet_vertices, dtype=np.float64)
    sv = np.asarray(surface_vertices, dtype=np.float64)
    faces = np.asarray(surface_faces, dtype=np.int32)
    diag = float(np.linalg.norm(sv.max(axis=0) - sv.min(axis=0)))
    with wp.ScopedDevice("cpu"):
        indices = wp.array(faces.reshape(-1), dtype=wp.int32)
        mesh = wp.Mesh(points=wp.array(sv, dtype=wp.vec3), indices=indices)
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
    if np.any(depth_np < 0):
        raise ValueError("distance query found no surface face for some tet vertices")
    grad_np /= np.linalg.norm(grad_np, axis=1, keepdims=True)
    return depth_np, grad_np

"""Self-intersection detection of a triangle surface: a Warp kernel over ``wp.Mesh`` BVH box queries.

Netgen silently makes no tets from a self-intersecting surface (it logs "boundary mesh is
overlapping"), so the coarse surface is checked before it is handed over. Candidate pairs come from the
BVH of the float32 ``wp.Mesh`` (face boxes padded by a small fraction of the diagonal); the exact test
(see :mod:`warpfem.kernels.intersect`) runs in float64.
"""

from __future__ import annotations

import numpy as np

BOX_PADDING = 1e-6
"""Query boxes are padded by this fraction of the bounding-box diagonal (covers float32 rounding)."""


def intersecting_faces(vertices: np.ndarray, faces: np.ndarray) -> tuple[int, np.ndarray]:
    """Find the pairs of faces of a surface that intersect each other, on the CPU device.

    Neighbours (sharing an edge) and coplanar pairs are not tested; faces sharing one corner count as
    intersecting only where they meet elsewhere too.

    Args:
        vertices: (n, 3) positions, any units.
        faces: (m, 3) vertex indices.

    Returns:
        ``(pairs, mask)``: the number of intersecting face pairs and an (m,) bool array marking every
        face involved in one.
    """
    import warp as wp

    from warpfem.kernels import intersect as K

    x = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int32)
    if len(f) < 2:
        return 0, np.zeros(len(f), dtype=bool)
    center = 0.5 * (x.max(axis=0) + x.min(axis=0))
    scale = float(np.linalg.norm(x.max(axis=0) - x.min(axis=0))) or 1.0
    x = (x - center) / scale  # float32 BVH boxes in a unit box, whatever the file's scale
    corners = x[f]
    pad = BOX_PADDING
    with wp.ScopedDevice("cpu"):
        mesh = wp.Mesh(points=wp.array(x, dtype=wp.vec3), indices=wp.array(f.reshape(-1), dtype=wp.int32))
        hits = wp.zeros(len(f), dtype=wp.int32)
        wp.launch(
            K.count_intersections,
            dim=len(f),
            inputs=[
                mesh.id,
                wp.array(x, dtype=wp.vec3d),
                wp.array(f, dtype=wp.vec3i),
                wp.array(corners.min(axis=1) - pad, dtype=wp.vec3),
                wp.array(corners.max(axis=1) + pad, dtype=wp.vec3),
            ],
            outputs=[hits],
        )
        counts = hits.numpy()
    return int(counts.sum()) // 2, counts > 0

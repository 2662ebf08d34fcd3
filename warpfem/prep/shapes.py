"""Procedural tet meshes for tests, examples and reference problems (no files needed)."""

from __future__ import annotations

import numpy as np

# Kuhn subdivision of the unit cube into 6 positively oriented tets sharing the diagonal 0-7
# (corner c = x + 2 y + 4 z).
_KUHN = np.array(
    [[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]],
    dtype=np.int64,
)


def box_tet_mesh(
    lower: tuple[float, float, float], upper: tuple[float, float, float], cells: tuple[int, int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """A conforming tet mesh of an axis-aligned box, 6 tets per cell.

    Args:
        lower: Box minimum corner (m).
        upper: Box maximum corner (m).
        cells: Cells along x, y, z (each >= 1).

    Returns:
        vertices (p, 3) float64 and positively oriented tets (6 nx ny nz, 4) int32.
    """
    nx, ny, nz = (int(c) for c in cells)
    axes = [np.linspace(lower[d], upper[d], cells[d] + 1) for d in range(3)]
    gx, gy, gz = np.meshgrid(*axes, indexing="ij")
    vertices = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)

    def vid(i, j, k):
        return (i * (ny + 1) + j) * (nz + 1) + k

    i, j, k = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    i, j, k = i.ravel(), j.ravel(), k.ravel()
    corners = np.stack([vid(i + (c & 1), j + ((c >> 1) & 1), k + ((c >> 2) & 1)) for c in range(8)], axis=1)
    tets = corners[:, _KUHN].reshape(-1, 4)
    d = vertices[tets[:, 1:]] - vertices[tets[:, :1]]
    flip = np.linalg.det(d) < 0
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    return vertices, tets.astype(np.int32)

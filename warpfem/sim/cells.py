"""The cells that embedded points (dense vertices, collision and skin points) interpolate over.

Linear tets are their own cells. A quadratic tet is split into eight linear sub-tets on its ten nodes (one at
each corner, four around the shortest diagonal of the octahedron of its edge nodes), so a point follows the
piecewise-linear interpolant of the quadratic field at twice the resolution of the corners. The dense mesh
and the contacts share it, so what the contacts hold is what is drawn. A point's weights in its sub-tet are
never negative inside the tet: a penalty force spread by them pushes every node it touches outward, which the
quadratic shape functions (negative at the corners over most of a face) would not.
"""

from __future__ import annotations

import numpy as np

from warpfem.kernels.embedding import CELLS_PER_QUADRATIC_TET

EDGES = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
"""A tet's edges as corner pairs, in the order of its edge nodes (``kernels.fem.vec6i``)."""

_CORNER_TETS = ((0, 4, 5, 6), (1, 7, 4, 8), (2, 5, 7, 9), (3, 6, 9, 8))
_DIAGONALS = (((4, 9), (5, 6, 8, 7)), ((5, 8), (4, 7, 9, 6)), ((6, 7), (4, 5, 9, 8)))
"""The octahedron's three diagonals (edge nodes of opposite edges) and the ring of edge nodes around each."""

SUB_TETS = np.array(
    [_CORNER_TETS + tuple((a, b, ring[k], ring[(k + 1) % 4]) for k in range(4)) for (a, b), ring in _DIAGONALS],
    np.int32,
)
"""(3, 8, 4) a quadratic tet's sub-tets as its local nodes (0-3 the corners, 4 + k the node of edge
``EDGES[k]``), for each choice of the octahedron's diagonal; each positively oriented where the tet is, an
eighth of its volume."""


def _node_weights() -> np.ndarray:
    """(10, 4) each local node's barycentric coordinates in its tet: the corners, then the edge midpoints."""
    eye = np.eye(4)
    return np.vstack([eye, [(eye[a] + eye[b]) / 2.0 for a, b in EDGES]])


_SUB_INVERSE = np.linalg.inv(np.transpose(_node_weights()[SUB_TETS], (0, 1, 3, 2)))
"""(3, 8, 4, 4) maps a point's weights in the tet to its weights in each sub-tet, per diagonal."""


_OPPOSITE = ((0, 1, 2, 3), (0, 2, 1, 3), (0, 3, 1, 2))
"""For each diagonal of :data:`_DIAGONALS`, the corners of its two edges: it joins their midpoints."""


def shortest_diagonals(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(q,) each tet's shortest octahedron diagonal (an index into :data:`SUB_TETS`) at ``vertices``.

    Around the shortest one the sub-tets are best shaped and the interpolant's error is smallest.
    """
    x = np.asarray(vertices, np.float64)[np.asarray(tets)]
    lengths = [np.linalg.norm(x[:, a] + x[:, b] - x[:, c] - x[:, d], axis=1) for a, b, c, d in _OPPOSITE]
    return np.argmin(np.column_stack(lengths), axis=1).astype(np.int8)


def sub_cells(tet: np.ndarray, bary: np.ndarray, diagonal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points given by their tet and barycentric weights there, as a sub-tet and weights in it.

    Args:
        tet: (n,) each point's tet.
        bary: (n, 4) its barycentric weights (may be negative: a point outside extrapolates).
        diagonal: (q,) each tet's diagonal (:func:`shortest_diagonals`).

    Returns:
        (n,) the cell ``8 tet + s`` of sub-tet ``s`` that holds the point (outside: the one it lies least far
        outside of), and (n, 4) its weights there.
    """
    tet = np.asarray(tet, np.int64)
    bary = np.asarray(bary, np.float64).reshape(-1, 4)
    local = np.einsum("nsij,nj->nsi", _SUB_INVERSE[np.asarray(diagonal)[tet]], bary)
    best = local.min(axis=2).argmax(axis=1)
    cell = CELLS_PER_QUADRATIC_TET * tet + best
    return cell.astype(np.int32), local[np.arange(len(bary)), best]


def cell_arrays(
    tets: np.ndarray, edges: np.ndarray, diagonal: np.ndarray, node_slots: np.ndarray, tet_body: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Quadratic tets' sub-tets: (8 q, 4) their nodes, (128 q) their matrix slots, (8 q) their bodies.

    ``diagonal`` is each tet's (:func:`shortest_diagonals`); ``node_slots`` its 10 x 10 node blocks' slots
    (-1 below the diagonal, as ``block_pattern`` makes them); a sub-tet's 4 x 4 slots are those of its nodes.
    """
    sub = SUB_TETS[np.asarray(diagonal)]  # (q, 8, 4) local nodes
    q = np.arange(len(tets))[:, None, None]
    nodes = np.hstack([tets, edges])
    cells = nodes[q, sub].reshape(-1, 4)
    slots = np.asarray(node_slots).reshape(-1, 10, 10)[q[..., None], sub[:, :, :, None], sub[:, :, None, :]]
    return cells.astype(np.int32), slots.reshape(-1).astype(np.int32), np.repeat(tet_body, CELLS_PER_QUADRATIC_TET)

"""Embedding of the dense surface in the coarse tet mesh (Kondo & Kanai, step 3).

Preprocessing (:func:`embed`) assigns every dense vertex to the tet containing it, or, for a vertex
outside every tet, to the tet around the nearest boundary face that extrapolates least, and stores its
barycentric coordinates in that tet (extrapolating, i.e. some negative, for outside vertices). Every output frame,
:func:`map_dense` rebuilds the dense vertices as those barycentric combinations of the current tet
vertex positions.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from warpfem.kernels import embedding as K

INSIDE_TOLERANCE = 1e-5
"""A point whose smallest barycentric coordinate in a tet is >= -this counts as inside it."""

BOX_PADDING = 1e-6
"""Tet bounding boxes are padded by this fraction of the mesh's bounding-box diagonal for the search."""


def edge_matrix_inverses(tet_vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Return Dm^-1 for every tet, Dm = [b-a, c-a, d-a] as columns (so l = Dm^-1 (p - a)).

    Args:
        tet_vertices: (p, 3) positions.
        tets: (q, 4) non-degenerate tets.

    Returns:
        (q, 3, 3) float64 inverse edge matrices, in 1/mesh units.
    """
    x = np.asarray(tet_vertices, dtype=np.float64)
    dm = np.stack([x[tets[:, k]] - x[tets[:, 0]] for k in (1, 2, 3)], axis=2)
    return np.linalg.inv(dm)


def barycentric(points: np.ndarray, tet_vertices: np.ndarray, tets: np.ndarray, tet_index: np.ndarray) -> np.ndarray:
    """Return the barycentric coordinates of each point in its assigned tet (float64).

    Args:
        points: (n, 3) positions.
        tet_vertices: (p, 3) positions.
        tets: (q, 4) tets.
        tet_index: (n,) tet of each point.

    Returns:
        (n, 4) coordinates summing to 1; all >= 0 exactly when the point is in the tet.
    """
    inv = edge_matrix_inverses(tet_vertices, tets)[tet_index]
    local = np.einsum("nij,nj->ni", inv, np.asarray(points, dtype=np.float64) - tet_vertices[tets[tet_index, 0]])
    return np.concatenate([1.0 - local.sum(axis=1, keepdims=True), local], axis=1)


def boundary_face_tets(tets: np.ndarray, boundary_faces: np.ndarray) -> np.ndarray:
    """Return, for each boundary face, the index of the tet having it as a face.

    Args:
        tets: (q, 4) tets.
        boundary_faces: (l, 3) triangles indexing the same vertices as ``tets``.

    Returns:
        (l,) int32 tet indices.

    Raises:
        ValueError: If a boundary face is not a face of any tet.
    """
    tet_faces = np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 2, 3]], tets[:, [0, 1, 3]], tets[:, [0, 1, 2]]])
    keys = np.sort(np.concatenate([tet_faces, boundary_faces]), axis=1)
    _, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    owner = np.full(inverse.max() + 1, -1, dtype=np.int64)
    owner[inverse[: len(tet_faces)]] = np.tile(np.arange(len(tets)), 4)
    face_tet = owner[inverse[len(tet_faces) :]]
    if np.any(face_tet < 0):
        raise ValueError(f"{int(np.sum(face_tet < 0))} boundary faces are not faces of any tet")
    return face_tet.astype(np.int32)


def outside_distance(tet_vertices: np.ndarray, tets: np.ndarray, tet: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Per embedded point, how far (in the mesh's units) it lies outside its tet; 0 inside.

    The distance past the farthest of the tet's face planes that its weights put it beyond: weight ``w_k < 0``
    places it ``-w_k h_k`` past the face opposite corner k, ``h_k`` the tet's height over that face (for a point
    beside a face, its distance to the tet).
    """
    corners = np.asarray(tet_vertices, dtype=np.float64)[np.asarray(tets)[np.asarray(tet)]]
    past = np.zeros(len(corners))
    for k in range(4):
        a, b, c = (corners[:, j] for j in range(4) if j != k)
        normal = np.cross(b - a, c - a)
        height = np.abs(np.einsum("ij,ij->i", corners[:, k] - a, normal)) / np.linalg.norm(normal, axis=1)
        past = np.maximum(past, -np.asarray(bary)[:, k] * height)
    return past


def embed(
    points: np.ndarray, tet_vertices: np.ndarray, tets: np.ndarray, boundary_faces: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Assign each point to a tet and compute its barycentric coordinates there (on the CPU device).

    A point inside the tet mesh (up to ``INSIDE_TOLERANCE`` in barycentric units) goes to the tet that
    contains it; any other point to the tet, of those touching a corner of the boundary face nearest to
    it, in which its weights' absolute values sum least (:func:`least_extrapolating`). Candidate tets come
    from a Warp BVH over the tets' boxes; the nearest face from a ``wp.Mesh`` query; the final
    coordinates are recomputed in float64.

    Args:
        points: (n, 3) positions to embed, in mesh units.
        tet_vertices: (p, 3) tet vertex positions.
        tets: (q, 4) positively oriented tets.
        boundary_faces: (l, 3) boundary triangles of the tet mesh, indexing ``tet_vertices``.

    Returns:
        ``(tet_index, bary)``: (n,) int32 tet of each point and (n, 4) float64 coordinates with
        ``points[i] == bary[i] @ tet_vertices[tets[tet_index[i]]]``.
    """
    points = np.asarray(points, dtype=np.float64)
    x = np.asarray(tet_vertices, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int32)
    boundary_faces = np.asarray(boundary_faces, dtype=np.int32)
    if len(points) == 0:
        return np.zeros(0, dtype=np.int32), np.zeros((0, 4))

    diag = float(np.linalg.norm(x.max(axis=0) - x.min(axis=0)))
    corners = x[tets]
    pad = BOX_PADDING * diag
    device = "cpu"
    with wp.ScopedDevice(device):
        lowers = wp.array(corners.min(axis=1) - pad, dtype=wp.vec3)
        uppers = wp.array(corners.max(axis=1) + pad, dtype=wp.vec3)
        bvh = wp.Bvh(lowers, uppers)
        mesh = wp.Mesh(points=wp.array(x, dtype=wp.vec3), indices=wp.array(boundary_faces.reshape(-1), dtype=wp.int32))
        tet_out = wp.empty(len(points), dtype=wp.int32)
        face_out = wp.empty(len(points), dtype=wp.int32)
        wp.launch(
            K.locate_points,
            dim=len(points),
            inputs=[
                wp.array(points, dtype=wp.vec3),
                bvh.id,
                wp.array(corners[:, 0], dtype=wp.vec3),
                wp.array(edge_matrix_inverses(x, tets), dtype=wp.mat33),
                mesh.id,
                wp.array(boundary_face_tets(tets, boundary_faces), dtype=wp.int32),
                INSIDE_TOLERANCE,
                1e30,
            ],
            outputs=[tet_out, face_out],
        )
        tet_index, face = tet_out.numpy(), face_out.numpy()
    if np.any(tet_index < 0):
        raise ValueError(f"{int(np.sum(tet_index < 0))} points could not be assigned to a tet")
    outside = np.flatnonzero(face >= 0)
    tet_index[outside] = least_extrapolating(points[outside], x, tets, boundary_faces[face[outside]])
    return tet_index, barycentric(points, x, tets, tet_index)


EMBED_CHUNK = 4096
"""Outside points whose candidate tets are weighed at once (bounds the temporary arrays)."""


def least_extrapolating(points: np.ndarray, x: np.ndarray, tets: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Per point outside the tets, the tet in which its weights' absolute values sum least.

    The candidates are the tets touching a corner of the point's nearest boundary face (``faces``, one
    per point). That sum bounds how much the point's mapped position magnifies its tet corners' motion (1 inside a
    tet): the tet owning the nearest face may be a sliver, whose weights for a point a little way off run
    to tens, so a small deformation of it throws the point far.
    """
    order = np.argsort(tets.reshape(-1), kind="stable")
    start = np.searchsorted(tets.reshape(-1)[order], np.arange(len(x) + 1))
    owner = order // 4  # owner[start[v]:start[v + 1]]: the tets around vertex v
    count = start[faces + 1] - start[faces]  # (n, 3)
    width = int(count.sum(axis=1).max(initial=1))
    inverse, origin = edge_matrix_inverses(x, tets), x[tets[:, 0]]
    best = np.empty(len(points), dtype=np.int32)
    for lo in range(0, len(points), EMBED_CHUNK):
        hi = min(lo + EMBED_CHUNK, len(points))
        candidates = np.full((hi - lo, width), -1, dtype=np.int64)
        for i in range(lo, hi):
            around = np.concatenate([owner[start[v] : start[v + 1]] for v in faces[i]])
            candidates[i - lo, : len(around)] = around
        valid = candidates >= 0
        c = np.where(valid, candidates, 0)
        local = np.einsum("nkij,nkj->nki", inverse[c], points[lo:hi, None, :] - origin[c])
        spread = np.abs(local).sum(axis=2) + np.abs(1.0 - local.sum(axis=2))
        best[lo:hi] = c[np.arange(hi - lo), np.where(valid, spread, np.inf).argmin(axis=1)]
    return best

"""A coarse surface that encloses the dense one (a cage), so every dense vertex lies inside a tet.

QEM places the simplified surface through the dense one, so half of the dense surface bulges out of the
coarse tets (0.5-4.5 % of a scan's size at default face counts). Contacts and colliders then act on a
surface the user does not see, and the dense vertices outside are extrapolated. :func:`enclose` pushes the
coarse vertices outward along their normals, each by what the dense vertices outside its faces need, a few
rounds, keeping the surface free of self-intersections; Netgen then fills the cage.
"""

from __future__ import annotations

import numpy as np

from warpfem.prep.surface import vertex_normals

ROUNDS = 8
"""Push rounds; each moves every vertex by what the dense vertices still outside its faces need."""

TOLERANCE = 2e-4
"""A dense vertex at most this far outside the cage (fraction of the bounding-box diagonal) counts as in."""

OVERSHOOT = 1.25
"""Each round pushes a vertex this much further than its faces' outside points need (vertex normals are
not face normals, so an exact push leaves the points just outside)."""


def outside_distances(
    points: np.ndarray, vertices: np.ndarray, faces: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Signed distance of each point to a closed surface (positive outside), its closest face and weights.

    The weights are the closest point's barycentric coordinates in that face (libigl).
    """
    import igl

    if len(points) == 0:
        return np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros((0, 3))
    s, face, closest, _ = igl.signed_distance(
        np.ascontiguousarray(points, dtype=np.float64),
        np.ascontiguousarray(vertices, dtype=np.float64),
        np.ascontiguousarray(faces, dtype=np.int64),
        sign_type=igl.SIGNED_DISTANCE_TYPE_FAST_WINDING_NUMBER,
    )
    a, b, c = (np.ascontiguousarray(vertices[faces[face, k]]) for k in range(3))
    bary = np.clip(igl.barycentric_coordinates(closest, a, b, c), 0.0, 1.0)
    return s, face, bary


def enclose(
    vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, intersects
) -> tuple[np.ndarray, dict[str, float]]:
    """Push a closed coarse surface outward until it contains ``points`` (the dense vertices).

    Args:
        vertices: (k, 3) coarse surface positions, in unit-diagonal coordinates.
        faces: (l, 3) outward coarse triangles.
        points: (n, 3) dense vertices to enclose, same coordinates.
        intersects: Returns whether a candidate surface ``(vertices, faces)`` intersects itself; a round
            that would make it do so is halved, then dropped.

    Returns:
        ``(vertices, stats)``: the cage (same faces) and ``cage_offset`` (largest vertex push),
        ``cage_outside`` (fraction of points still more than :data:`TOLERANCE` outside) and
        ``cage_outside_max`` (the farthest of them), both relative to the bounding-box diagonal.
    """
    v = np.asarray(vertices, dtype=np.float64).copy()
    faces = np.asarray(faces, dtype=np.int64)
    candidates = np.arange(len(points))
    for _ in range(ROUNDS):
        s, face, bary = outside_distances(points[candidates], v, faces)
        out = s > TOLERANCE
        candidates = candidates[out]
        if not out.any():
            break
        # corner k of the closest face moves s b_k / |b|^2, so the face moves s at the closest point
        share = s[out, None] * bary[out] / np.sum(bary[out] ** 2, axis=1, keepdims=True)
        push = np.zeros(len(v))
        for k in range(3):
            np.maximum.at(push, faces[face[out], k], share[:, k])
        normals = vertex_normals(v, faces)
        for fraction in (1.0, 0.5):
            moved = v + (fraction * OVERSHOOT * push)[:, None] * normals
            if not intersects(moved, faces):
                v = moved
                break
        else:
            break
    s, _, _ = outside_distances(points[candidates], v, faces)
    outside = s[s > TOLERANCE]
    stats = {
        "cage_offset": float(np.linalg.norm(v - vertices, axis=1).max()) if len(v) else 0.0,
        "cage_outside": float(len(outside) / max(len(points), 1)),
        "cage_outside_max": float(outside.max()) if len(outside) else 0.0,
    }
    return v, stats

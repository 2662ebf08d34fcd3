"""Embedding of dense surface points in a tet mesh: point location and the per-frame map.

Points are located in the tets while preprocessing, and in a quadratic tet's cells while contacts are found.

A point p in tet t with corners (a, b, c, d) has barycentric coordinates (1 - l0 - l1 - l2, l0, l1, l2)
with l = Dm^-1 (p - a), Dm = [b-a, c-a, d-a]. It lies in the tet when all four are >= 0.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated

CELLS_PER_QUADRATIC_TET = wp.constant(8)
"""Sub-tets a quadratic tet is cut into (``warpfem.sim.cells``): cell ``8 e + s`` is sub-tet ``s`` of tet ``e``."""


@wp.func
def deformation_gradient(x: wp.array(dtype=wp.vec3), t: wp.vec4i, dm_inv: wp.mat33) -> wp.mat33:
    """``F = Ds Dm^-1`` of the tet with corners ``t`` at positions ``x`` (``dm_inv``: its rest ``Dm^-1``)."""
    o = x[t[0]]
    return wp.matrix_from_cols(x[t[1]] - o, x[t[2]] - o, x[t[3]] - o) * dm_inv


@wp.func
def min_barycentric(dm_inv: wp.mat33, origin: wp.vec3, p: wp.vec3) -> float:
    """Smallest barycentric coordinate of ``p`` in the tet with corner ``origin`` and inverse edge matrix."""
    w = dm_inv * (p - origin)
    return wp.min(wp.min(1.0 - w[0] - w[1] - w[2], w[0]), wp.min(w[1], w[2]))


@wp.kernel
def locate_points(
    points: wp.array(dtype=wp.vec3),
    tet_bvh: wp.uint64,
    tet_origin: wp.array(dtype=wp.vec3),
    tet_dm_inv: wp.array(dtype=wp.mat33),
    boundary_mesh: wp.uint64,
    face_tet: wp.array(dtype=wp.int32),
    tolerance: float,
    max_dist: float,
    tet_out: wp.array(dtype=wp.int32),
    face_out: wp.array(dtype=wp.int32),
):
    """Find each point's tet (-1 if none) and, for a point outside the tets, the nearest boundary face.

    The tet is the candidate (from the BVH of tet boxes) whose smallest barycentric coordinate is
    largest, if that is >= -tolerance (``face_out`` -1); otherwise the tet owning the nearest boundary
    face (``face_out`` that face).
    """
    i = wp.tid()
    p = points[i]
    query = wp.bvh_query_aabb(tet_bvh, p, p)
    t = wp.int32(0)
    best = wp.int32(-1)
    best_score = wp.float32(-1.0e30)
    while wp.bvh_query_next(query, t):
        score = min_barycentric(tet_dm_inv[t], tet_origin[t], p)
        if score > best_score:
            best_score = score
            best = t
    face_out[i] = -1
    if best >= 0 and best_score >= -tolerance:
        tet_out[i] = best
    else:
        hit = wp.mesh_query_point_no_sign(boundary_mesh, p, max_dist)
        if hit.result:
            tet_out[i] = face_tet[hit.face]
            face_out[i] = hit.face
        else:
            tet_out[i] = -1


@wp.func
def interpolate(field: wp.array(dtype=wp.vec3), tet: wp.vec4i, w: wp.vec4) -> wp.vec3:
    """sum_k w[k] * field[tet[k]]: a per-vertex field at a point with barycentric weights w in the tet."""
    return w[0] * field[tet[0]] + w[1] * field[tet[1]] + w[2] * field[tet[2]] + w[3] * field[tet[3]]


@wp.func
def tet_weights(q: wp.vec3, inverse: wp.mat33, origin: wp.vec3) -> wp.vec4:
    """Barycentric weights of ``q`` in a tet, from its inverse edge matrix and first corner."""
    b = inverse * (q - origin)
    return wp.vec4(1.0 - b[0] - b[1] - b[2], b[0], b[1], b[2])


@wp.func
def in_cell(
    q: wp.vec3,
    e: int,
    t: wp.vec4i,
    w: wp.vec4,
    x: wp.array(dtype=wp.vec3),
    cells: wp.array(dtype=wp.vec4i),
    rest_x: wp.array(dtype=wp.vec3),
    dm_inv: wp.array(dtype=wp.mat33),
):
    """The cell of tet ``e`` (corners ``t``) that holds ``q`` (weights ``w`` in the tet), and where ``q`` is.

    Returns ``(c, mu, lam)``: the cell, ``q``'s weights in it at the current positions (which the contact's
    force and Jacobian use), and the tet weights of the material point there at rest (which its depth uses).
    Linear tets are their own cells (all three are ``e`` and ``w``); of a quadratic tet's eight sub-tets, the
    one ``q`` lies least far outside of, since the curved tet's sub-tets, not its corners, place its nodes'
    material (and its dense surface).
    """
    if cells.shape[0] == dm_inv.shape[0]:
        return e, w, w
    best_c = e * CELLS_PER_QUADRATIC_TET
    best_mu = w
    best = float(-1.0e30)
    for s in range(CELLS_PER_QUADRATIC_TET):
        c = e * CELLS_PER_QUADRATIC_TET + s
        n = cells[c]
        o = x[n[0]]
        edges = wp.matrix_from_cols(x[n[1]] - o, x[n[2]] - o, x[n[3]] - o)
        if wp.determinant(edges) != 0.0:
            mu = tet_weights(q, wp.inverse(edges), o)
            score = wp.min(mu)
            if score > best:
                best = score
                best_c = c
                best_mu = mu
    rest = interpolate(rest_x, cells[best_c], best_mu)
    return best_c, best_mu, tet_weights(rest, dm_inv[e], rest_x[t[0]])


@wp.kernel
def map_dense(
    cells: wp.array(dtype=wp.vec4i),
    positions: wp.array(dtype=wp.vec3),
    dense_cell: wp.array(dtype=wp.int32),
    dense_bary: wp.array(dtype=wp.vec4),
    dense_out: wp.array(dtype=wp.vec3),
):
    """Dense point i = sum_k bary[i][k] * positions[cells[dense_cell[i]][k]] (extrapolates outside the cell)."""
    i = wp.tid()
    dense_out[i] = interpolate(positions, cells[dense_cell[i]], dense_bary[i])

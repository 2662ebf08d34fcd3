"""Depth below a body's visible surface during a step.

The distance field's gradients turned with each tet (Kondo & Kanai step 7), the surface faces' lattice of
depths below the visible surface (filled by preprocessing in the layout of :mod:`warpfem.kernels.distance`),
and the dense surface itself at rest.
"""

import warp as wp

from .distance import LATTICE, LATTICE_POINTS
from .embedding import deformation_gradient, interpolate


@wp.func
def add_rotated_gradients(
    t: wp.vec4i, R: wp.mat33, rest_grad: wp.array(dtype=wp.vec3), grad_out: wp.array(dtype=wp.vec3)
):
    """grad[v] += R g0[v] for the four corners v of a tet turned by R (Kondo & Kanai step 7, unnormalised)."""
    for a in range(4):
        wp.atomic_add(grad_out, t[a], R * rest_grad[t[a]])


@wp.func
def direction_at(grad: wp.array(dtype=wp.vec3), v: int) -> wp.vec3:
    """normalize(sum_k R_k g0) at tet vertex v from the accumulated sum (zero stays zero)."""
    g = grad[v]
    n = wp.length(g)
    if n > 0.0:
        return g / n
    return g


@wp.func
def interpolate_directions(grad: wp.array(dtype=wp.vec3), tet: wp.vec4i, w: wp.vec4) -> wp.vec3:
    """The rotated gradients of a tet's corners, each normalised, blended with barycentric weights w."""
    return (
        w[0] * direction_at(grad, tet[0])
        + w[1] * direction_at(grad, tet[1])
        + w[2] * direction_at(grad, tet[2])
        + w[3] * direction_at(grad, tet[3])
    )


@wp.func
def lattice_index(i: int, j: int) -> int:
    """Position of lattice point (i, j) in a face's row-by-row list."""
    return i * (LATTICE + 1) - i * (i - 1) // 2 + j


@wp.func
def lattice_cell(w1: float, w2: float):
    """The lattice cell (i, j) at face weights w1, w2 (of corners 1 and 2), and the offsets in it (cell units)."""
    u = w1 * float(LATTICE)
    v = w2 * float(LATTICE)
    i = wp.min(int(u), LATTICE - 1)
    j = wp.min(int(v), LATTICE - 1 - i)
    return i, j, u - float(i), v - float(j)


@wp.func
def lattice_depth(face_depth: wp.array(dtype=float), face_id: int, w1: float, w2: float) -> float:
    """The face's lattice depths interpolated (linearly on the lattice's triangles) at weights w1, w2."""
    i, j, fu, fv = lattice_cell(w1, w2)
    base = face_id * LATTICE_POINTS
    d00 = face_depth[base + lattice_index(i, j)]
    d10 = face_depth[base + lattice_index(i + 1, j)]
    d01 = face_depth[base + lattice_index(i, j + 1)]
    if fu + fv <= 1.0:
        return (1.0 - fu - fv) * d00 + fu * d10 + fv * d01
    d11 = face_depth[base + lattice_index(i + 1, j + 1)]
    return (fu + fv - 1.0) * d11 + (1.0 - fv) * d10 + (1.0 - fu) * d01


@wp.func
def face_weights(r: wp.vec3, e1: wp.vec3, e2: wp.vec3, c: wp.vec3) -> wp.vec2:
    """Weights of corners 1 and 2 of ``r``'s projection on a face, clamped to it (``r`` from corner 0, c = e1 x e2)."""
    area2 = wp.dot(c, c)
    w1 = wp.clamp(wp.dot(wp.cross(r, e2), c) / area2, 0.0, 1.0)
    w2 = wp.clamp(wp.dot(wp.cross(e1, r), c) / area2, 0.0, 1.0 - w1)
    return wp.vec2(w1, w2)


@wp.func
def face_query(x: wp.array(dtype=wp.vec3), face_depth: wp.array(dtype=float), face_id: int, face: wp.vec3i, q: wp.vec3):
    """``q`` against an outward-wound surface face: normal, depth below its plane and below the visible surface.

    Returns the face's outward normal, ``q``'s depth below its plane and below the visible surface near it
    (m), and ``q``'s distance to (about) the face's nearest point (m). The visible surface's depth is the
    plane's plus the visible surface's depth below the face at ``q``'s projection, clamped to the face
    (interpolated on the face's lattice: negative where the face is part of a cage around a dense surface,
    zero where the face is the visible surface).
    """
    a = x[face[0]]
    e1 = x[face[1]] - a
    e2 = x[face[2]] - a
    c = wp.cross(e1, e2)
    n = wp.normalize(c)
    w = face_weights(q - a, e1, e2, c)
    plane = wp.dot(n, a - q)
    depth = plane + lattice_depth(face_depth, face_id, w[0], w[1])
    return n, plane, depth, wp.length(q - (a + w[0] * e1 + w[1] * e2))


@wp.func
def exit_face(
    x: wp.array(dtype=wp.vec3),
    face_depth: wp.array(dtype=float),
    tet_face_ids: wp.array(dtype=wp.int32),
    tet_faces: wp.array(dtype=wp.vec3i),
    f0: int,
    f1: int,
    q: wp.vec3,
    step: wp.vec3,
):
    """Of a tet's surface faces ``f0`` to ``f1``, the one ``q`` leaves through.

    That is the nearest whose plane ``q`` would cross moving by ``step`` (m, its motion relative to the tet over
    a step), else the nearest. Returns that face's depth and outward normal (:func:`face_query`), the cage's
    margin there over the visible surface (m, zero where the face is the visible surface) and the nearest
    face's index.
    """
    entered = float(1.0e30)
    nearest = float(1.0e30)
    d = float(0.0)
    g = wp.vec3()
    margin = float(0.0)
    d_near = float(0.0)
    g_near = wp.vec3()
    margin_near = float(0.0)
    f_near = f0
    for f in range(f0, f1):
        n_f, plane, depth_f, dist = face_query(x, face_depth, tet_face_ids[f], tet_faces[f], q)
        if plane > 0.0 and plane - wp.dot(n_f, step) <= 0.0 and dist < entered:
            entered = dist
            d = depth_f
            g = n_f
            margin = plane - depth_f
        if dist < nearest:
            nearest = dist
            d_near = depth_f
            g_near = n_f
            margin_near = plane - depth_f
            f_near = f
    if entered == 1.0e30:
        return d_near, g_near, margin_near, f_near
    return d, g, margin, f_near


@wp.struct
class VisibleSurface:
    """Each body's dense surface at rest, for the exact depth of a point found inside one of its tets.

    A point at barycentric weights ``w`` in tet ``t`` lies at ``sum_k w_k X[t_k]`` in the body's rest shape;
    its depth there below the dense rest surface (a ``wp.Mesh``) is its depth below the visible surface,
    the small strain of the tet aside. Bodies that are copies of one another (the same prepared mesh, moved,
    turned and scaled) share one mesh: ``to_mesh`` and ``mesh_origin`` take a rest position to the mesh's
    frame, ``mesh_scale`` takes a length there back to metres.
    """

    rest_x: wp.array(dtype=wp.vec3)
    dm_inv: wp.array(dtype=wp.mat33)  # per tet, its rest shape matrix inverted
    tet_body: wp.array(dtype=wp.int32)
    mesh: wp.array(dtype=wp.uint64)  # per body; 0: no dense surface (the tets' surface is the visible one)
    to_mesh: wp.array(dtype=wp.mat33)  # per body
    mesh_origin: wp.array(dtype=wp.vec3)  # per body
    mesh_scale: wp.array(dtype=float)  # per body, m per mesh unit
    reach: wp.array(dtype=float)  # per body, the farthest the query looks (mesh units)
    offset: float  # added to a contact's depth in a body with a dense surface (m), capped by the cage's margin


@wp.func
def visible_depth(
    s: VisibleSurface,
    x: wp.array(dtype=wp.vec3),
    e: int,
    t: wp.vec4i,
    w: wp.vec4,
    d: float,
    g: wp.vec3,
    bound: float,
    offset: float,
):
    """Depth (m, negative outside) and way out below its body's dense surface of a point in tet ``e``, plus ``offset``.

    The point lies at weights ``w`` in the tet; the way out is the way to the nearest surface point at rest,
    carried to the tet's current shape at positions ``x`` as a normal is (by the inverse transpose of its
    deformation gradient). ``bound`` (m) bounds the point's depth from above (the face lattice's
    :func:`depth_above`): a point inside lies no farther than that from the surface, so
    the query looks no farther than that and ``offset`` (m, a contact's start outside the surface) outside it,
    and a point with no surface that near lies outside (0 returned). ``d``, ``g`` are returned where the body has
    no dense surface (and so no offset), and ``d`` plus the offset where, beyond the bound, no surface lies
    within its reach of the point.
    """
    b = s.tet_body[e]
    mesh = s.mesh[b]
    if mesh == wp.uint64(0):
        return d, g
    q = s.to_mesh[b] * interpolate(s.rest_x, t, w) + s.mesh_origin[b]
    near = (wp.max(bound, 0.0) + offset) / s.mesh_scale[b] * 1.0001 + 1.0e-5 * s.reach[b]  # float slack
    hit = wp.mesh_query_point_sign_normal(mesh, q, wp.min(near, s.reach[b]))
    if not hit.result:
        if near < s.reach[b]:
            return 0.0, g
        return d + offset, g
    to_surface = wp.mesh_eval_position(mesh, hit.face, hit.u, hit.v) - q
    dist = wp.length(to_surface)
    out = wp.mesh_eval_face_normal(mesh, hit.face)
    if dist > 1.0e-6 * s.reach[b]:
        out = -hit.sign * to_surface / dist
    depth = offset - hit.sign * dist * s.mesh_scale[b]
    shape = deformation_gradient(x, t, s.dm_inv[e])
    if wp.determinant(shape) <= 0.0:
        return depth, g
    return depth, wp.normalize(wp.transpose(wp.inverse(shape)) * (wp.transpose(s.to_mesh[b]) * out))


@wp.func
def contact_offset(
    p: int,
    e: int,
    t: wp.vec4i,
    w: wp.vec4,
    q: wp.vec3,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    dt: float,
    tet_face_start: wp.array(dtype=wp.int32),
    tet_faces: wp.array(dtype=wp.vec3i),
    tet_face_ids: wp.array(dtype=wp.int32),
    face_depth: wp.array(dtype=float),
    s: VisibleSurface,
    point_velocity: wp.array(dtype=wp.vec3),
) -> float:
    """How far outside the dense surface a contact of point p (at q, weights w in surface tet e) starts (m).

    The body's offset, capped by the cage's margin over the visible surface at the face the point leaves
    through (:func:`exit_face`): it fades to none where that face is the visible surface, since no tet holds
    a point in a gap beyond it, and a contact there would come and go.
    """
    if s.offset == 0.0:
        return 0.0
    step = dt * (point_velocity[p] - interpolate(v, t, w))
    f0 = tet_face_start[e]
    _d, _g, margin, _f = exit_face(x, face_depth, tet_face_ids, tet_faces, f0, tet_face_start[e + 1], q, step)
    return wp.min(s.offset, wp.max(margin, 0.0))


@wp.func
def depth_above(
    rest_x: wp.array(dtype=wp.vec3), face_depth: wp.array(dtype=float), face: wp.vec3i, face_id: int, q: wp.vec3
):
    """An upper bound (m) on the depth of rest position ``q`` below the visible surface, from a surface face.

    The face's lattice holds the signed distance to the dense rest surface, which changes by at most the
    distance moved: below it by at most ``q``'s distance from a corner of the face's cell nearest ``q``, all
    at rest (``rest_x``). Negative: ``q`` surely lies outside the visible surface.
    """
    a = rest_x[face[0]]
    e1 = rest_x[face[1]] - a
    e2 = rest_x[face[2]] - a
    w = face_weights(q - a, e1, e2, wp.cross(e1, e2))
    i, j, fu, fv = lattice_cell(w[0], w[1])
    r = q - (a + (float(i) * e1 + float(j) * e2) / float(LATTICE))  # from the cell's corner (i, j)
    base = face_id * LATTICE_POINTS
    bound = face_depth[base + lattice_index(i, j)] + wp.length(r)
    bound = wp.min(bound, face_depth[base + lattice_index(i + 1, j)] + wp.length(r - e1 / float(LATTICE)))
    return wp.min(bound, face_depth[base + lattice_index(i, j + 1)] + wp.length(r - e2 / float(LATTICE)))

"""Implicit (backward) Euler: per-vertex system assembly, static colliders, position update, NaN guard.

The linearised backward-Euler step solves for the new velocity v+:
``((1 + dt alpha) M + (dt^2 + dt beta) K + dt^2 K_c + dt C_friction) v+ = M v + dt (f_el + M g + f_c)``
where K is the warped stiffness (assembled by the FEM kernel), alpha/beta the Rayleigh coefficients and
K_c, C_friction, f_c the static colliders' penalty and friction (the ground is a plane collider), on the
tet vertices and on the skin (the dense vertices outside the tets, whose terms reach the tet's corners).
"""

import warp as wp

from .embedding import interpolate
from .grid import warp_sum_at

# static collider kinds
PLANE = wp.constant(0)
SPHERE = wp.constant(1)
BOX = wp.constant(2)

# a tangential speed below this (m/s) counts as sticking when the friction coefficient is computed
FRICTION_SPEED_EPS = 1.0e-3


@wp.func
def collider_distance(kind: int, center: wp.vec3, size: wp.vec3, p: wp.vec3) -> wp.vec4:
    """Signed distance (m, negative inside) of ``p`` to a static collider and its outward unit normal.

    Plane: ``center`` is a point on it, ``size`` its normal. Sphere: radius ``size[0]``. Box: axis-aligned,
    half extents ``size``.
    """
    if kind == PLANE:
        return wp.vec4(wp.dot(size, p - center), size[0], size[1], size[2])
    d = p - center
    if kind == SPHERE:
        r = wp.length(d)
        n = wp.vec3(0.0, 1.0, 0.0)
        if r > 0.0:
            n = d / r
        return wp.vec4(r - size[0], n[0], n[1], n[2])
    q = wp.vec3(wp.abs(d[0]) - size[0], wp.abs(d[1]) - size[1], wp.abs(d[2]) - size[2])
    s = wp.vec3(wp.sign(d[0]), wp.sign(d[1]), wp.sign(d[2]))
    outside = wp.vec3(wp.max(q[0], 0.0), wp.max(q[1], 0.0), wp.max(q[2], 0.0))
    if wp.length(outside) > 0.0:
        n = wp.normalize(wp.cw_mul(outside, s))
        return wp.vec4(wp.length(outside), n[0], n[1], n[2])
    # inside: leave through the nearest face
    axis = int(0)
    if q[1] > q[axis]:
        axis = 1
    if q[2] > q[axis]:
        axis = 2
    n = wp.vec3()
    n[axis] = s[axis]
    return wp.vec4(q[axis], n[0], n[1], n[2])


@wp.func
def within_step(depth: float, n: wp.vec3, vp: wp.vec3, v_body: wp.vec3, dt: float) -> bool:
    """Whether a point ``depth`` below a collider's surface (normal ``n``) acts with it this step.

    Below the surface, or crossing it within the step at its own speed or at its body's, which drags it
    along: the speculative contact test.
    """
    return depth - dt * wp.min(wp.dot(n, vp), wp.dot(n, v_body)) > 0.0


@wp.func
def static_contact(
    kind: int,
    center: wp.vec3,
    size: wp.vec3,
    response: wp.vec2,
    p: wp.vec3,
    vp: wp.vec3,
    v_body: wp.vec3,
    m: float,
    dt: float,
):
    """A static collider's penalty force ``k pen n`` and matrix term on a point of mass ``m`` (both zero if none).

    The collider (stiffness k per unit mass and friction mu in ``response``) acts on a point below its
    surface, or about to cross it within this step at its own speed or at its body's, which drags it along
    (speculative contact): the penalty k m depth n, dt^2 k m n n^T in the matrix (above the surface only this
    velocity term acts, which damps the approach and never attracts), and implicit friction dt c (I - n n^T),
    c = mu k m depth / |v_t|.
    """
    dn = collider_distance(kind, center, size, p)
    n = wp.vec3(dn[1], dn[2], dn[3])
    depth = -dn[0]
    force = wp.vec3()
    block = wp.mat33()
    if within_step(depth, n, vp, v_body, dt):
        k = response[0] * m
        pen = wp.max(depth, 0.0)
        force = k * pen * n
        nn = wp.outer(n, n)
        vt = vp - wp.dot(vp, n) * n
        c = response[1] * k * pen / wp.max(wp.length(vt), FRICTION_SPEED_EPS)
        block = dt * dt * k * nn + dt * c * (wp.identity(n=3, dtype=float) - nn)
    return force, block


@wp.kernel
def body_momentum(
    v: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    vertex_body: wp.array(dtype=wp.int32),
    momentum_out: wp.array(dtype=wp.vec3),
):
    """Each body's momentum (kg m/s), summed over its vertices into a zeroed array (one atomic per warp)."""
    i = wp.tid()
    warp_sum_at(mass[i] * v[i], vertex_body[i], momentum_out)


@wp.kernel
def build_system(
    # inputs: state
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    # inputs: model
    mass: wp.array(dtype=float),
    alpha: wp.array(dtype=float),
    free: wp.array(dtype=wp.int32),
    diag_slot: wp.array(dtype=wp.int32),
    vertex_depth: wp.array(dtype=float),
    # inputs: forces and parameters
    force: wp.array(dtype=wp.vec3),
    gravity: wp.array(dtype=wp.vec3),
    collider_kind: wp.array(dtype=wp.int32),
    collider_center: wp.array(dtype=wp.vec3),
    collider_size: wp.array(dtype=wp.vec3),
    collider_response: wp.array(dtype=wp.vec2),
    dv: wp.array(dtype=wp.vec3),
    vertex_body: wp.array(dtype=wp.int32),
    body_momentum: wp.array(dtype=wp.vec3),
    body_mass: wp.array(dtype=float),
    dt: float,
    # outputs
    matrix_out: wp.array(dtype=wp.mat33),
    rhs_out: wp.array(dtype=wp.vec3),
    diag_inv_out: wp.array(dtype=wp.mat33),
    v_guess_out: wp.array(dtype=wp.vec3),
    direction_out: wp.array(dtype=wp.vec3),
):
    """Adds mass, damping and static-collider terms to the diagonal block, builds the right-hand side and M^-1.

    Each static collider acts on the vertex as :func:`static_contact` says: its force on the right-hand side,
    its matrix term in the diagonal block; not on a vertex outside the visible surface (a corner of the cage
    around a dense surface, whose samples meet the colliders instead).
    """
    i = wp.tid()
    m = mass[i]
    vi = v[i]
    xi = x[i]
    ident = wp.identity(n=3, dtype=float)
    slot = diag_slot[i]
    block = matrix_out[slot] + (1.0 + dt * alpha[i]) * m * ident
    rhs = m * vi + dt * (force[i] + m * gravity[0])

    b = vertex_body[i]
    v_body = body_momentum[b] / body_mass[b]
    if vertex_depth[i] >= 0.0:
        for o in range(collider_kind.shape[0]):
            f, s = static_contact(
                collider_kind[o], collider_center[o], collider_size[o], collider_response[o], xi, vi, v_body, m, dt
            )
            rhs += dt * f
            block += s

    matrix_out[slot] = block
    if free[i] == 0:
        rhs_out[i] = wp.vec3()
        v_guess_out[i] = wp.vec3()
        direction_out[i] = wp.vec3()
        diag_inv_out[i] = wp.mat33()
    else:
        rhs_out[i] = rhs
        v_guess_out[i] = vi
        d = dv[i]
        direction_out[i] = wp.where(wp.isfinite(d), d, wp.vec3())  # a blown-up step must not poison the next
        diag_inv_out[i] = wp.inverse(block)


@wp.func
def add_symmetric(
    matrix_out: wp.array(dtype=wp.mat33),
    tet_slots: wp.array(dtype=wp.int32),
    e: int,
    w: wp.vec4,
    block: wp.mat33,
):
    """Add ``w_a w_b block`` to every stored block (a, b) of tet ``e`` (a symmetric term of one embedded point)."""
    for a in range(4):
        for b in range(4):
            slot = tet_slots[e * 16 + a * 4 + b]
            if slot >= 0:
                wp.atomic_add(matrix_out, slot, (w[a] * w[b]) * block)


@wp.kernel
def skin_colliders(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    tets: wp.array(dtype=wp.vec4i),
    tet_slots: wp.array(dtype=wp.int32),
    skin_tet: wp.array(dtype=wp.int32),
    skin_bary: wp.array(dtype=wp.vec4),
    skin_mass: wp.array(dtype=float),
    tet_body: wp.array(dtype=wp.int32),
    body_momentum: wp.array(dtype=wp.vec3),
    body_mass: wp.array(dtype=float),
    collider_kind: wp.array(dtype=wp.int32),
    collider_center: wp.array(dtype=wp.vec3),
    collider_size: wp.array(dtype=wp.vec3),
    collider_response: wp.array(dtype=wp.vec2),
    dt: float,
    force_out: wp.array(dtype=wp.vec3),
    matrix_out: wp.array(dtype=wp.mat33),
):
    """The static colliders acting on the skin: dense vertices that lie outside the coarse tets.

    The same :func:`static_contact` as a vertex gets, at a point embedded in a tet (``x_p = sum w_k x_k``):
    its force goes to the corners by the weights ``w`` and its matrix term ``S`` to the tet's blocks as
    ``w_a w_b S`` (the weights of an outside point extrapolate, so some are
    negative; the term stays symmetric positive semi-definite).
    """
    i = wp.tid()
    e = skin_tet[i]
    t = tets[e]
    w = skin_bary[i]
    xp = interpolate(x, t, w)
    vp = interpolate(v, t, w)
    body = tet_body[e]
    v_body = body_momentum[body] / body_mass[body]
    for o in range(collider_kind.shape[0]):
        f, s = static_contact(
            collider_kind[o],
            collider_center[o],
            collider_size[o],
            collider_response[o],
            xp,
            vp,
            v_body,
            skin_mass[i],
            dt,
        )
        if wp.trace(s) > 0.0:  # in contact (the matrix term is positive whenever the collider acts)
            for c in range(4):
                wp.atomic_add(force_out, t[c], w[c] * f)
            add_symmetric(matrix_out, tet_slots, e, w, s)


@wp.func
def late_contact(
    kind: int,
    center: wp.vec3,
    size: wp.vec3,
    response: wp.vec2,
    p: wp.vec3,
    vp: wp.vec3,
    vp_new: wp.vec3,
    v_body: wp.vec3,
    m: float,
    dt: float,
):
    """A static contact the step's first solve would cross without having counted it (zero force and block if none).

    A point that :func:`static_contact` left free (not within one step of the surface at the step's start
    speeds) but whose new velocity carries it below the surface by the step's end: it gets the penalty's
    matrix term ``dt^2 k m n n^T`` and the force ``k m depth n`` at its (negative) start depth, so the second
    solve brings it to the surface by the step's end instead of through it.
    """
    dn = collider_distance(kind, center, size, p)
    n = wp.vec3(dn[1], dn[2], dn[3])
    depth = -dn[0]
    force = wp.vec3()
    block = wp.mat33()
    if not within_step(depth, n, vp, v_body, dt) and depth - dt * wp.dot(n, vp_new) > 0.0:
        k = response[0] * m
        force = k * depth * n
        block = dt * dt * k * wp.outer(n, n)
    return force, block


@wp.kernel
def late_vertex_contacts(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    v_new: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    free: wp.array(dtype=wp.int32),
    diag_slot: wp.array(dtype=wp.int32),
    vertex_depth: wp.array(dtype=float),
    collider_kind: wp.array(dtype=wp.int32),
    collider_center: wp.array(dtype=wp.vec3),
    collider_size: wp.array(dtype=wp.vec3),
    collider_response: wp.array(dtype=wp.vec2),
    vertex_body: wp.array(dtype=wp.int32),
    body_momentum: wp.array(dtype=wp.vec3),
    body_mass: wp.array(dtype=float),
    dt: float,
    late_out: wp.array(dtype=wp.int32),
    count_out: wp.array(dtype=wp.int32),
    matrix_out: wp.array(dtype=wp.mat33),
    rhs_out: wp.array(dtype=wp.vec3),
):
    """:func:`late_contact` on each free tet vertex inside the visible surface not yet given one this step.

    Adds to its right-hand side and diagonal block, marks it in ``late_out`` and counts it in ``count_out[0]``.
    """
    i = wp.tid()
    if free[i] == 0 or vertex_depth[i] < 0.0 or late_out[i] != 0:
        return
    b = vertex_body[i]
    v_body = body_momentum[b] / body_mass[b]
    for o in range(collider_kind.shape[0]):
        f, s = late_contact(
            collider_kind[o], collider_center[o], collider_size[o], collider_response[o], x[i], v[i], v_new[i],
            v_body, mass[i], dt,
        )  # fmt: skip
        if wp.trace(s) > 0.0:
            rhs_out[i] = rhs_out[i] + dt * f
            matrix_out[diag_slot[i]] = matrix_out[diag_slot[i]] + s
            late_out[i] = 1
            wp.atomic_add(count_out, 0, 1)


@wp.kernel
def late_skin_contacts(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    v_new: wp.array(dtype=wp.vec3),
    tets: wp.array(dtype=wp.vec4i),
    tet_slots: wp.array(dtype=wp.int32),
    free: wp.array(dtype=wp.int32),
    skin_tet: wp.array(dtype=wp.int32),
    skin_bary: wp.array(dtype=wp.vec4),
    skin_mass: wp.array(dtype=float),
    tet_body: wp.array(dtype=wp.int32),
    body_momentum: wp.array(dtype=wp.vec3),
    body_mass: wp.array(dtype=float),
    collider_kind: wp.array(dtype=wp.int32),
    collider_center: wp.array(dtype=wp.vec3),
    collider_size: wp.array(dtype=wp.vec3),
    collider_response: wp.array(dtype=wp.vec2),
    dt: float,
    late_out: wp.array(dtype=wp.int32),
    count_out: wp.array(dtype=wp.int32),
    matrix_out: wp.array(dtype=wp.mat33),
    rhs_out: wp.array(dtype=wp.vec3),
):
    """:func:`late_contact` on each skin point not yet given one this step.

    Its force goes to the right-hand side of its tet's free corners by the weights, ``w_a w_b S`` to the
    tet's blocks; it is marked and counted as in :func:`late_vertex_contacts`.
    """
    i = wp.tid()
    if late_out[i] != 0:
        return
    e = skin_tet[i]
    t = tets[e]
    w = skin_bary[i]
    body = tet_body[e]
    v_body = body_momentum[body] / body_mass[body]
    for o in range(collider_kind.shape[0]):
        f, s = late_contact(
            collider_kind[o], collider_center[o], collider_size[o], collider_response[o], interpolate(x, t, w),
            interpolate(v, t, w), interpolate(v_new, t, w), v_body, skin_mass[i], dt,
        )  # fmt: skip
        if wp.trace(s) > 0.0:
            for c in range(4):
                if free[t[c]] != 0:
                    wp.atomic_add(rhs_out, t[c], dt * w[c] * f)
            add_symmetric(matrix_out, tet_slots, e, w, s)
            late_out[i] = 1
            wp.atomic_add(count_out, 0, 1)


@wp.kernel
def refresh_preconditioner(
    free: wp.array(dtype=wp.int32),
    diag_slot: wp.array(dtype=wp.int32),
    matrix: wp.array(dtype=wp.mat33),
    diag_inv_out: wp.array(dtype=wp.mat33),
):
    """The inverse diagonal blocks again, after late contacts changed them (zero on pinned vertices)."""
    i = wp.tid()
    if free[i] != 0:
        diag_inv_out[i] = wp.inverse(matrix[diag_slot[i]])


@wp.kernel
def advance_positions(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    v_new: wp.array(dtype=wp.vec3),
    dt: float,
    x_out: wp.array(dtype=wp.vec3),
    dv_out: wp.array(dtype=wp.vec3),
    bad_vertex_out: wp.array(dtype=wp.int32),
):
    """x+ = x + dt v+ and dv = v+ - v; records the lowest vertex index whose position or velocity is not finite."""
    i = wp.tid()
    vi = v_new[i]
    xi = x[i] + dt * vi
    x_out[i] = xi
    dv_out[i] = vi - v[i]
    if not (wp.isfinite(xi) and wp.isfinite(vi)):
        wp.atomic_min(bad_vertex_out, 0, i)

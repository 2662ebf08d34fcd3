"""The rigid correction: each stiff body's momentum solved exactly where float32 loses it in CG.

A step's rigid motions ``u + w x y`` of a body (``y`` from its first vertex) solve the system without its
elastic part (masses, damping, contacts), whose force and torque the elastic part leaves alone. A body that
nothing holds or touches solves its own 6x6 system (:func:`rigid_correct`); bodies touching one another solve
theirs together, coupled by the contacts between them, by a block-Jacobi PCG on their rigid motions
(:func:`coupled_pairs` and the ``coupled_*`` kernels), so that a stack of stiff bodies keeps its momentum too.
"""

import warp as wp

from .product import mat43, pair_terms

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated


@wp.func
def mark_pair(
    k: int,
    count: wp.array(dtype=wp.int32),
    verts_a: wp.array(dtype=wp.vec4i),
    verts_b: wp.array(dtype=wp.vec4i),
    vertex_body: wp.array(dtype=wp.int32),
    paired_out: wp.array(dtype=wp.int32),
):
    """Marks both bodies of contact pair k where it is live (k below ``count[0]`` and the capacity)."""
    if k < wp.min(count[0], verts_a.shape[0]):
        paired_out[vertex_body[verts_a[k][0]]] = 1
        paired_out[vertex_body[verts_b[k][0]]] = 1


@wp.kernel
def mark_touched_pairs(
    count: wp.array(dtype=wp.int32),
    verts_a: wp.array(dtype=wp.vec4i),
    verts_b: wp.array(dtype=wp.vec4i),
    vertex_body: wp.array(dtype=wp.int32),
    paired_out: wp.array(dtype=wp.int32),
):
    """Marks both bodies of each live contact pair."""
    mark_pair(wp.tid(), count, verts_a, verts_b, vertex_body, paired_out)


@wp.kernel
def rigid_sums(
    x: wp.array(dtype=wp.vec3),
    v_start: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    rhs_base: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    alpha: wp.array(dtype=float),
    vertex_body: wp.array(dtype=wp.int32),
    body_first: wp.array(dtype=wp.int32),
    held: wp.array(dtype=wp.int32),
    dt: float,
    weight_out: wp.array(dtype=float),
    moment_out: wp.array(dtype=wp.vec3),
    force_out: wp.array(dtype=wp.vec3),
    torque_out: wp.array(dtype=wp.vec3),
    second_out: wp.array(dtype=wp.mat33),
    momentum_out: wp.array(dtype=wp.vec3),
    spin_out: wp.array(dtype=wp.vec3),
):
    """Per body without held vertices, the sums its rigid correction needs.

    With positions ``y`` taken from the body's first vertex: damped masses d, d y, the residual
    r = rhs_base - d v of the system without elasticity, y x r, d y y^T, and the momentum d v and its moment
    y x d v at the step's start (``v_start``).
    """
    i = wp.tid()
    b = vertex_body[i]
    if held[b] != 0:
        return
    d = (1.0 + dt * alpha[i]) * mass[i]
    y = x[i] - x[body_first[b]]
    r = rhs_base[i] - d * v[i]
    p = d * v_start[i]
    wp.atomic_add(weight_out, b, d)
    wp.atomic_add(moment_out, b, d * y)
    wp.atomic_add(force_out, b, r)
    wp.atomic_add(torque_out, b, wp.cross(y, r))
    wp.atomic_add(second_out, b, d * wp.outer(y, y))
    wp.atomic_add(momentum_out, b, p)
    wp.atomic_add(spin_out, b, wp.cross(y, p))


@wp.kernel
def rigid_contact_sums(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    row_start: wp.array(dtype=wp.int32),
    cols: wp.array(dtype=wp.int32),
    diag_slot: wp.array(dtype=wp.int32),
    matrix_base: wp.array(dtype=wp.mat33),
    mass: wp.array(dtype=float),
    alpha: wp.array(dtype=float),
    vertex_body: wp.array(dtype=wp.int32),
    body_first: wp.array(dtype=wp.int32),
    held: wp.array(dtype=wp.int32),
    dt: float,
    force_out: wp.array(dtype=wp.vec3),
    torque_out: wp.array(dtype=wp.vec3),
    kuu_out: wp.array(dtype=wp.mat33),
    kuw_out: wp.array(dtype=wp.mat33),
    kww_out: wp.array(dtype=wp.mat33),
):
    """Per body without held vertices, what its contacts' own blocks add to the rigid correction, row by row.

    The system without elasticity less its damped masses is the static contacts' blocks C (a vertex's on its
    diagonal, a skin point's spread over its cell's corners). A rigid velocity ``u + w x y`` (y from the
    body's first vertex) maps through J_a = [I, -[y_a]x], so C adds J^T C J to the 6x6 system (in blocks
    uu, uw, ww) and -J^T C v to the residual's force and torque.
    """
    a = wp.tid()
    body = vertex_body[a]
    if held[body] != 0:
        return
    origin = x[body_first[body]]
    ya = wp.skew(x[a] - origin)
    f = wp.vec3()
    t = wp.vec3()
    kuu = wp.mat33()
    kuw = wp.mat33()
    kww = wp.mat33()
    for slot in range(row_start[a], row_start[a + 1]):
        b = cols[slot]
        B = matrix_base[slot]
        if slot == diag_slot[a]:
            B = B - (1.0 + dt * alpha[a]) * mass[a] * wp.identity(n=3, dtype=float)
        yb = wp.skew(x[b] - origin)
        fa = B * v[b]
        f -= fa
        t -= ya * fa
        kuu += B
        kuw -= B * yb
        kww -= ya * B * yb
        if b != a:
            Bt = wp.transpose(B)
            fb = Bt * v[a]
            f -= fb
            t -= yb * fb
            kuu += Bt
            kuw -= Bt * ya
            kww -= yb * Bt * ya
    wp.atomic_add(force_out, body, f)
    wp.atomic_add(torque_out, body, t)
    wp.atomic_add(kuu_out, body, kuu)
    wp.atomic_add(kuw_out, body, kuw)
    wp.atomic_add(kww_out, body, kww)


@wp.kernel
def rigid_correct(
    x: wp.array(dtype=wp.vec3),
    vertex_body: wp.array(dtype=wp.int32),
    body_first: wp.array(dtype=wp.int32),
    held: wp.array(dtype=wp.int32),
    paired: wp.array(dtype=wp.int32),
    weight: wp.array(dtype=float),
    moment: wp.array(dtype=wp.vec3),
    force: wp.array(dtype=wp.vec3),
    torque: wp.array(dtype=wp.vec3),
    second: wp.array(dtype=wp.mat33),
    momentum: wp.array(dtype=wp.vec3),
    spin: wp.array(dtype=wp.vec3),
    kuu: wp.array(dtype=wp.mat33),
    kuw: wp.array(dtype=wp.mat33),
    kww: wp.array(dtype=wp.mat33),
    dt: float,
    turn_limit: float,
    v_out: wp.array(dtype=wp.vec3),
):
    """Moves the velocities of a body that nothing holds or touches by its residual's rigid motion.

    The rigid motion ``u + w x y`` that zeroes its residual's force and torque solves the 6x6 system of the
    damped masses and the static contacts (:func:`rigid_contact_sums`), by its Schur complement on ``w``. In
    flight (no static contact) the torque is balanced only while the body turns less than ``turn_limit``
    (rad) a step: a step's velocities turn a body along the chord of its rotation, whose moment falls short
    of its angular momentum as the turn grows, so no torque balance holds for a fast spin; its momentum then
    changes by exactly the impulse of gravity and damping. A body on a collider is always balanced: its
    contacts, not its spin, set its turn.
    """
    i = wp.tid()
    b = vertex_body[i]
    if held[b] != 0 or paired[b] != 0:
        return
    total = weight[b]
    c = moment[b] / total
    ident = wp.identity(n=3, dtype=float)
    s = second[b]
    inertia = (wp.trace(s) * ident - s) - total * (wp.dot(c, c) * ident - wp.outer(c, c))
    k_uu = total * ident + kuu[b]
    k_uw = -wp.skew(moment[b]) + kuw[b]
    k_ww = (wp.trace(s) * ident - s) + kww[b]
    uu_inv = wp.inverse(k_uu)
    turn = wp.vec3()
    schur = k_ww - wp.transpose(k_uw) * uu_inv * k_uw
    if wp.determinant(inertia) > 0.0 and wp.determinant(schur) > 0.0:
        flight = wp.trace(kuu[b]) <= 1.0e-5 * total  # no static contact (its blocks: rounding at most)
        if not flight or wp.length(wp.inverse(inertia) * (spin[b] - wp.cross(c, momentum[b]))) * dt < turn_limit:
            turn = wp.inverse(schur) * (torque[b] - wp.transpose(k_uw) * (uu_inv * force[b]))
    u = uu_inv * (force[b] - k_uw * turn)
    v_out[i] = v_out[i] + u + wp.cross(turn, x[i] - x[body_first[b]])


@wp.func
def body_block(
    b: int,
    weight: wp.array(dtype=float),
    moment: wp.array(dtype=wp.vec3),
    second: wp.array(dtype=wp.mat33),
    kuu: wp.array(dtype=wp.mat33),
    kuw: wp.array(dtype=wp.mat33),
    kww: wp.array(dtype=wp.mat33),
):
    """Body b's 6x6 block of the system without elasticity on its rigid motions, as uu, uw, ww blocks."""
    ident = wp.identity(n=3, dtype=float)
    s = second[b]
    return weight[b] * ident + kuu[b], -wp.skew(moment[b]) + kuw[b], (wp.trace(s) * ident - s) + kww[b]


@wp.func
def block_solve(k_uu: wp.mat33, k_uw: wp.mat33, k_ww: wp.mat33, f: wp.vec3, t: wp.vec3):
    """The rigid motion answering ``(f, t)`` through a 6x6 block (Schur complement on the spin).

    Zero where the block is not positive definite.
    """
    u = wp.vec3()
    w = wp.vec3()
    if wp.determinant(k_uu) > 0.0:
        uu_inv = wp.inverse(k_uu)
        schur = k_ww - wp.transpose(k_uw) * uu_inv * k_uw
        if wp.determinant(schur) > 0.0:
            w = wp.inverse(schur) * (t - wp.transpose(k_uw) * (uu_inv * f))
            u = uu_inv * (f - k_uw * w)
    return u, w


@wp.func
def coupled_body(held: wp.array(dtype=wp.int32), paired: wp.array(dtype=wp.int32), b: int) -> bool:
    """Whether body b's rigid motion is an unknown of the coupled solve: touching another, holding none."""
    return paired[b] != 0 and held[b] == 0


@wp.func
def corner_velocity(
    i: int,
    v: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    vertex_body: wp.array(dtype=wp.int32),
    body_first: wp.array(dtype=wp.int32),
    held: wp.array(dtype=wp.int32),
    paired: wp.array(dtype=wp.int32),
    rigid: int,
    pu: wp.array(dtype=wp.vec3),
    pw: wp.array(dtype=wp.vec3),
) -> wp.vec3:
    """Vertex i's velocity: ``v``, or with ``rigid`` its body's rigid motion ``pu + pw x y``.

    A body that is not an unknown of the coupled solve stays: zero.
    """
    if rigid == 0:
        return v[i]
    b = vertex_body[i]
    if not coupled_body(held, paired, b):
        return wp.vec3()
    return pu[b] + wp.cross(pw[b], x[i] - x[body_first[b]])


@wp.kernel
def coupled_pairs(
    count: wp.array(dtype=wp.int32),
    verts_a: wp.array(dtype=wp.vec4i),
    weights_a: wp.array(dtype=wp.vec4),
    verts_b: wp.array(dtype=wp.vec4i),
    weights_b: wp.array(dtype=wp.vec4),
    matrix: wp.array(dtype=wp.mat33),
    v: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    vertex_body: wp.array(dtype=wp.int32),
    body_first: wp.array(dtype=wp.int32),
    held: wp.array(dtype=wp.int32),
    paired: wp.array(dtype=wp.int32),
    rigid: int,
    pu: wp.array(dtype=wp.vec3),
    pw: wp.array(dtype=wp.vec3),
    sign: float,
    force_out: wp.array(dtype=wp.vec3),
    torque_out: wp.array(dtype=wp.vec3),
):
    """``sign`` times each live pair's term of A on the velocities, into the coupled bodies' force and torque.

    The term is ``J^T C J`` less its diagonal blocks (:func:`kernels.product.pair_terms`, as CG applies it),
    which the system without elasticity holds; the
    velocities are ``v``, or with ``rigid`` the bodies' motions ``pu``, ``pw``. Only the bodies that are
    unknowns of the coupled solve take a share.
    """
    k = wp.tid()
    if k >= count[0]:
        return
    ia = verts_a[k]
    ib = verts_b[k]
    Ua = mat43()
    Ub = mat43()
    for c in range(4):
        Ua[c] = corner_velocity(ia[c], v, x, vertex_body, body_first, held, paired, rigid, pu, pw)
        Ub[c] = corner_velocity(ib[c], v, x, vertex_body, body_first, held, paired, rigid, pu, pw)
    Da, Db, unused = pair_terms(Ua, Ub, weights_a[k], weights_b[k], matrix[k])
    body_a = vertex_body[ia[0]]
    body_b = vertex_body[ib[0]]
    for c in range(4):
        if coupled_body(held, paired, body_a):
            wp.atomic_add(force_out, body_a, sign * Da[c])
            wp.atomic_add(torque_out, body_a, sign * wp.cross(x[ia[c]] - x[body_first[body_a]], Da[c]))
        if coupled_body(held, paired, body_b):
            wp.atomic_add(force_out, body_b, sign * Db[c])
            wp.atomic_add(torque_out, body_b, sign * wp.cross(x[ib[c]] - x[body_first[body_b]], Db[c]))


@wp.struct
class RigidSums:
    """Per body: the damped masses' sums and the contacts' own blocks, and which bodies are unknowns.

    The sums of :func:`rigid_sums` and :func:`rigid_contact_sums`; a body is an unknown of the coupled solve
    where it touches another and holds no vertex.
    """

    weight: wp.array(dtype=float)
    moment: wp.array(dtype=wp.vec3)
    second: wp.array(dtype=wp.mat33)
    kuu: wp.array(dtype=wp.mat33)
    kuw: wp.array(dtype=wp.mat33)
    kww: wp.array(dtype=wp.mat33)
    held: wp.array(dtype=wp.int32)
    paired: wp.array(dtype=wp.int32)


@wp.struct
class Krylov:
    """The coupled solve's vectors, two vec3 per body each (motion and spin), and its scalars per iteration."""

    zu: wp.array(dtype=wp.vec3)
    zw: wp.array(dtype=wp.vec3)
    ru: wp.array(dtype=wp.vec3)
    rw: wp.array(dtype=wp.vec3)
    pu: wp.array(dtype=wp.vec3)
    pw: wp.array(dtype=wp.vec3)
    qu: wp.array(dtype=wp.vec3)
    qw: wp.array(dtype=wp.vec3)
    su: wp.array(dtype=wp.vec3)
    sw: wp.array(dtype=wp.vec3)
    rs: wp.array(dtype=float)
    pq: wp.array(dtype=float)


@wp.func
def precondition(b: int, m: RigidSums, k: Krylov):
    """s = (body b's block)^-1 r; returns r.s."""
    k_uu, k_uw, k_ww = body_block(b, m.weight, m.moment, m.second, m.kuu, m.kuw, m.kww)
    su, sw = block_solve(k_uu, k_uw, k_ww, k.ru[b], k.rw[b])
    k.su[b] = su
    k.sw[b] = sw
    return wp.dot(k.ru[b], su) + wp.dot(k.rw[b], sw)


@wp.kernel
def coupled_start(m: RigidSums, force: wp.array(dtype=wp.vec3), torque: wp.array(dtype=wp.vec3), k: Krylov):
    """z = 0, r = the residual's force and torque (pairs included), s = M^-1 r, p = s; r.s into rs[0]."""
    b = wp.tid()
    k.zu[b] = wp.vec3()
    k.zw[b] = wp.vec3()
    if not coupled_body(m.held, m.paired, b):
        k.ru[b] = wp.vec3()
        k.rw[b] = wp.vec3()
        k.pu[b] = wp.vec3()
        k.pw[b] = wp.vec3()
        return
    k.ru[b] = force[b]
    k.rw[b] = torque[b]
    rs = precondition(b, m, k)
    k.pu[b] = k.su[b]
    k.pw[b] = k.sw[b]
    wp.atomic_add(k.rs, 0, rs)


@wp.kernel
def coupled_blocks(m: RigidSums, k: Krylov):
    """q = (each body's own block) p: the coupled operator less its pairs (:func:`coupled_pairs` adds them)."""
    b = wp.tid()
    q_u = wp.vec3()
    q_w = wp.vec3()
    if coupled_body(m.held, m.paired, b):
        k_uu, k_uw, k_ww = body_block(b, m.weight, m.moment, m.second, m.kuu, m.kuw, m.kww)
        q_u = k_uu * k.pu[b] + k_uw * k.pw[b]
        q_w = wp.transpose(k_uw) * k.pu[b] + k_ww * k.pw[b]
    k.qu[b] = q_u
    k.qw[b] = q_w


@wp.kernel
def coupled_curvature(m: RigidSums, k: Krylov, it: int):
    """p.q into pq[it]."""
    b = wp.tid()
    if coupled_body(m.held, m.paired, b):
        wp.atomic_add(k.pq, it, wp.dot(k.pu[b], k.qu[b]) + wp.dot(k.pw[b], k.qw[b]))


@wp.kernel
def coupled_step(m: RigidSums, k: Krylov, it: int):
    """z += alpha p, r -= alpha q, s = M^-1 r; r.s into rs[it + 1] (alpha = rs[it] / pq[it], 0 at a breakdown)."""
    b = wp.tid()
    if not coupled_body(m.held, m.paired, b):
        return
    a = float(0.0)
    if k.pq[it] > 0.0 and k.rs[it] > 0.0:
        a = k.rs[it] / k.pq[it]
    k.zu[b] = k.zu[b] + a * k.pu[b]
    k.zw[b] = k.zw[b] + a * k.pw[b]
    k.ru[b] = k.ru[b] - a * k.qu[b]
    k.rw[b] = k.rw[b] - a * k.qw[b]
    wp.atomic_add(k.rs, it + 1, precondition(b, m, k))


@wp.kernel
def coupled_direction(m: RigidSums, k: Krylov, it: int):
    """p = s + beta p with beta = rs[it + 1] / rs[it] (0 at a breakdown)."""
    b = wp.tid()
    if not coupled_body(m.held, m.paired, b):
        return
    beta = float(0.0)
    if k.rs[it] > 0.0:
        beta = k.rs[it + 1] / k.rs[it]
    k.pu[b] = k.su[b] + beta * k.pu[b]
    k.pw[b] = k.sw[b] + beta * k.pw[b]


@wp.kernel
def coupled_apply(
    x: wp.array(dtype=wp.vec3),
    vertex_body: wp.array(dtype=wp.int32),
    body_first: wp.array(dtype=wp.int32),
    m: RigidSums,
    k: Krylov,
    v_out: wp.array(dtype=wp.vec3),
):
    """Moves the velocities of each body of the coupled solve by its rigid motion ``z``."""
    i = wp.tid()
    b = vertex_body[i]
    if coupled_body(m.held, m.paired, b):
        v_out[i] = v_out[i] + k.zu[b] + wp.cross(k.zw[b], x[i] - x[body_first[b]])

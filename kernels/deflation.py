"""Rigid motions taken out of CG for bodies in flight stiffer than float32 resolves at their step.

For such a body (E dt^2 / (rho h^2) near 1e7 or more) float32's rounding of the stiffness blocks is a share of
its vertices' mass or more, so the product A p is noise along its rigid motions, the system's smallest modes:
block-Jacobi CG stalls at its cap there, or diverges. The iteration then leaves those motions alone: its
preconditioner is ``P D P^T`` with ``P = I - G W G^T M`` per body, which removes from the preconditioned residual
its rigid part in the mass norm (``G`` maps a body's velocity and spin ``(v, w)`` to ``v + w x y`` at its vertices,
``y`` from the body's first vertex; ``M`` the lumped masses; ``W = (G^T M G)^-1``). CG then solves the
deformation in a few dozen iterations, and the rigid motions come from the rigid correction after it, from the
system without its elastic part, which holds them exactly (``warpfem.sim.rigid.RigidCorrection``). Only a body
in flight: a contact ties its rigid motion to its deformation, which the split would then get wrong.
"""

import warp as wp

from .cg import block_sum, is_active, iteration_step, update_row

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated


@wp.func
def lever(x: wp.array(dtype=wp.vec3), body_first: wp.array(dtype=wp.int32), b: int, i: int) -> wp.vec3:
    """Vertex i's position from its body's first vertex (m)."""
    return x[i] - x[body_first[b]]


@wp.kernel
def deflation_contacts(
    matrix_base: wp.array(dtype=wp.mat33),
    diag_slot: wp.array(dtype=wp.int32),
    mass: wp.array(dtype=float),
    alpha: wp.array(dtype=float),
    vertex_body: wp.array(dtype=wp.int32),
    dt: float,
    touching_out: wp.array(dtype=wp.int32),
):
    """Marks the body of a vertex whose diagonal block holds more than its damped mass: a contact's share."""
    i = wp.tid()
    d = (1.0 + dt * alpha[i]) * mass[i]
    if wp.trace(matrix_base[diag_slot[i]]) > 3.0 * d * (1.0 + 1.0e-5):
        touching_out[vertex_body[i]] = 1


@wp.kernel
def deflation_active(
    held: wp.array(dtype=wp.int32),
    touching: wp.array(dtype=wp.int32),
    rate: wp.array(dtype=float),
    rounding: float,
    gate: float,
    active_out: wp.array(dtype=wp.int32),
):
    """Per body: deflated where ``rounding`` times its stiffness ``rate`` exceeds ``gate``, in flight.

    In flight: no contact, no held vertex. The touching marks are cleared for the next solve.
    """
    b = wp.tid()
    active_out[b] = wp.where(held[b] == 0 and touching[b] == 0 and rounding * rate[b] > gate, 1, 0)
    touching[b] = 0


@wp.kernel
def deflation_reset(
    force_out: wp.array(dtype=wp.vec3),
    torque_out: wp.array(dtype=wp.vec3),
    kuu_out: wp.array(dtype=wp.mat33),
    kuw_out: wp.array(dtype=wp.mat33),
    kww_out: wp.array(dtype=wp.mat33),
):
    """Zero a solve's sums (four sets, one thread per entry) and the bodies' mass blocks."""
    i = wp.tid()
    force_out[i] = wp.vec3()
    torque_out[i] = wp.vec3()
    if i < kuu_out.shape[0]:
        kuu_out[i] = wp.mat33()
        kuw_out[i] = wp.mat33()
        kww_out[i] = wp.mat33()


@wp.kernel
def deflation_masses(
    x: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    vertex_body: wp.array(dtype=wp.int32),
    body_first: wp.array(dtype=wp.int32),
    active: wp.array(dtype=wp.int32),
    kuu_out: wp.array(dtype=wp.mat33),
    kuw_out: wp.array(dtype=wp.mat33),
    kww_out: wp.array(dtype=wp.mat33),
):
    """Vertex i's share of its body's ``G^T M G`` in blocks uu, uw, ww (``G_i = [I, -[y_i]x]``)."""
    i = wp.tid()
    b = vertex_body[i]
    if active[b] == 0:
        return
    m = mass[i]
    y = wp.skew(lever(x, body_first, b, i))
    wp.atomic_add(kuu_out, b, m * wp.identity(n=3, dtype=float))
    wp.atomic_add(kuw_out, b, -m * y)
    wp.atomic_add(kww_out, b, -m * (y * y))


@wp.kernel
def deflation_factor(
    active: wp.array(dtype=wp.int32),
    kuu: wp.array(dtype=wp.mat33),
    kuw: wp.array(dtype=wp.mat33),
    kww: wp.array(dtype=wp.mat33),
    uu_inv_out: wp.array(dtype=wp.mat33),
    schur_inv_out: wp.array(dtype=wp.mat33),
):
    """Per active body, the factors of ``W``: ``kuu^-1`` and its Schur complement's inverse on the spin."""
    b = wp.tid()
    uu_inv = wp.mat33()
    schur_inv = wp.mat33()
    if active[b] != 0:
        uu_inv = wp.inverse(kuu[b])
        schur_inv = wp.inverse(kww[b] - wp.transpose(kuw[b]) * uu_inv * kuw[b])
    uu_inv_out[b] = uu_inv
    schur_inv_out[b] = schur_inv


@wp.func
def rigid_part(
    i: int,
    b: int,
    base: int,
    force: wp.array(dtype=wp.vec3),
    torque: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    body_first: wp.array(dtype=wp.int32),
    uu_inv: wp.array(dtype=wp.mat33),
    kuw: wp.array(dtype=wp.mat33),
    schur_inv: wp.array(dtype=wp.mat33),
) -> wp.vec3:
    """``(G W s)_i`` for body b's sums ``s`` (force and torque at ``base + b``): the rigid velocity they give."""
    f = force[base + b]
    t = torque[base + b]
    spin = schur_inv[b] * (t - wp.transpose(kuw[b]) * (uu_inv[b] * f))
    return uu_inv[b] * (f - kuw[b] * spin) + wp.cross(spin, lever(x, body_first, b, i))


@wp.func
def add_moments(
    i: int,
    b: int,
    value: wp.vec3,
    x: wp.array(dtype=wp.vec3),
    body_first: wp.array(dtype=wp.int32),
    base: int,
    force_out: wp.array(dtype=wp.vec3),
    torque_out: wp.array(dtype=wp.vec3),
):
    """Adds ``value`` (row i) to body b's ``G^T`` sums at ``base + b``: force, and torque about its first vertex."""
    wp.atomic_add(force_out, base + b, value)
    wp.atomic_add(torque_out, base + b, wp.cross(lever(x, body_first, b, i), value))


@wp.struct
class Deflation:
    """What the deflated iteration reads: the bodies, their factors of ``W`` and the sums.

    The sums are four sets of ``bodies`` entries: r's, then ``M D P^T r``'s, by the iteration's parity.
    """

    x: wp.array(dtype=wp.vec3)
    mass: wp.array(dtype=float)
    vertex_body: wp.array(dtype=wp.int32)
    body_first: wp.array(dtype=wp.int32)
    active: wp.array(dtype=wp.int32)
    uu_inv: wp.array(dtype=wp.mat33)
    kuw: wp.array(dtype=wp.mat33)
    schur_inv: wp.array(dtype=wp.mat33)
    force: wp.array(dtype=wp.vec3)
    torque: wp.array(dtype=wp.vec3)


@wp.func
def sum_residual(i: int, r: wp.vec3, d: Deflation, parity: int):
    """Row i's share of its body's ``G^T r`` (set ``parity``), where the body is deflated."""
    b = d.vertex_body[i]
    if d.active[b] != 0:
        add_moments(i, b, r, d.x, d.body_first, parity * d.active.shape[0], d.force, d.torque)


@wp.func
def jacobi_row(i: int, r: wp.vec3, diag_inv: wp.array(dtype=wp.mat33), d: Deflation, parity: int) -> wp.vec3:
    """Row i of ``q = D P^T r`` (``P^T r = r - M G W G^T r``); adds ``G^T M q`` to its body's set 2 + parity."""
    b = d.vertex_body[i]
    nb = d.active.shape[0]
    if d.active[b] == 0:
        return diag_inv[i] * r
    m = d.mass[i]
    q = diag_inv[i] * (
        r - m * rigid_part(i, b, parity * nb, d.force, d.torque, d.x, d.body_first, d.uu_inv, d.kuw, d.schur_inv)
    )
    add_moments(i, b, m * q, d.x, d.body_first, (2 + parity) * nb, d.force, d.torque)
    return q


@wp.func
def project_row(i: int, q: wp.vec3, d: Deflation, parity: int) -> wp.vec3:
    """Row i of ``u = P q = q - G W G^T M q`` (the sums of set 2 + parity)."""
    b = d.vertex_body[i]
    if d.active[b] == 0:
        return q
    nb = d.active.shape[0]
    return q - rigid_part(i, b, (2 + parity) * nb, d.force, d.torque, d.x, d.body_first, d.uu_inv, d.kuw, d.schur_inv)


@wp.func
def clear_other(i: int, d: Deflation, parity: int):
    """The first vertex of each body zeroes the other parity's sums, for the next iteration."""
    b = d.vertex_body[i]
    if i == d.body_first[b]:
        nb = d.active.shape[0]
        other = 1 - parity
        d.force[other * nb + b] = wp.vec3()
        d.torque[other * nb + b] = wp.vec3()
        d.force[(2 + other) * nb + b] = wp.vec3()
        d.torque[(2 + other) * nb + b] = wp.vec3()


@wp.kernel
def deflation_start_sums(n: int, free: wp.array(dtype=wp.int32), r: wp.array(dtype=wp.vec3), d: Deflation):
    """The start's ``G^T r`` per deflated body (set 0)."""
    i = wp.tid()
    if i < n and free[i] != 0:
        sum_residual(i, r[i], d, 0)


@wp.kernel
def deflation_jacobi(
    n: int,
    free: wp.array(dtype=wp.int32),
    diag_inv: wp.array(dtype=wp.mat33),
    r: wp.array(dtype=wp.vec3),
    d: Deflation,
    iteration: wp.array(dtype=wp.int32),
    step: int,
    gamma: wp.array(dtype=float),
    bz: wp.array(dtype=float),
    tolerance: wp.array(dtype=float),
    max_iterations: wp.array(dtype=wp.int32),
    alpha: wp.array(dtype=float),
    u_out: wp.array(dtype=wp.vec3),
):
    """u = D P^T r for the residual of iteration k + 1 = iteration + step (``step`` -1: the start's)."""
    i = wp.tid()
    k = iteration[0] + step
    run = True
    if step >= 0:
        run = is_active(k, gamma, bz, tolerance[0], max_iterations[0]) and alpha[k] > 0.0
    if run and i < n and free[i] != 0:
        u_out[i] = jacobi_row(i, r[i], diag_inv, d, (k + 1) % 2)


@wp.kernel
def deflation_project(
    n: int,
    free: wp.array(dtype=wp.int32),
    diag_inv: wp.array(dtype=wp.mat33),
    r: wp.array(dtype=wp.vec3),
    d: Deflation,
    iteration: wp.array(dtype=wp.int32),
    step: int,
    gamma: wp.array(dtype=float),
    bz: wp.array(dtype=float),
    tolerance: wp.array(dtype=float),
    max_iterations: wp.array(dtype=wp.int32),
    alpha: wp.array(dtype=float),
    u_out: wp.array(dtype=wp.vec3),
    gamma_out: wp.array(dtype=float),
):
    """u = P u and r.u into gamma[k + 1] (``step`` -1: the start's, replacing the r.D r ``cg_init`` put there)."""
    i = wp.tid()
    k = iteration[0] + step
    run = True
    if step >= 0:
        run = is_active(k, gamma, bz, tolerance[0], max_iterations[0]) and alpha[k] > 0.0
    dot = float(0.0)
    if run and i < n:
        parity = (k + 1) % 2
        if free[i] != 0:
            u = project_row(i, u_out[i], d, parity)
            u_out[i] = u
            dot = wp.dot(r[i], u)
            if step < 0:
                dot -= wp.dot(r[i], diag_inv[i] * r[i])
        clear_other(i, d, parity)
    block_sum(dot, gamma_out, k + 1)


@wp.kernel
def deflation_update(
    n: int,
    diag_inv: wp.array(dtype=wp.mat33),
    iteration: wp.array(dtype=wp.int32),
    step: int,
    gamma: wp.array(dtype=float),
    delta: wp.array(dtype=float),
    bz: wp.array(dtype=float),
    tolerance: wp.array(dtype=float),
    max_iterations: wp.array(dtype=wp.int32),
    free: wp.array(dtype=wp.int32),
    d: Deflation,
    alpha_out: wp.array(dtype=float),
    done_out: wp.array(dtype=wp.int32),
    x_out: wp.array(dtype=wp.vec3),
    r_out: wp.array(dtype=wp.vec3),
    u_out: wp.array(dtype=wp.vec3),
    p_out: wp.array(dtype=wp.vec3),
    s_out: wp.array(dtype=wp.vec3),
    w_out: wp.array(dtype=wp.vec3),
):
    """``kernels.cg.cg_update`` without its dot: the new r's ``G^T r`` per deflated body instead.

    The sums go to the set of k + 1's parity; :func:`deflation_jacobi` and :func:`deflation_project` then make
    u and r.u.
    """
    i = wp.tid()
    k = iteration[0] + step
    a, beta = iteration_step(i, k, gamma, delta, bz, tolerance, max_iterations, alpha_out, done_out)
    if i < n and a > 0.0:
        update_row(i, a, beta, diag_inv, free, x_out, r_out, u_out, p_out, s_out, w_out)
        if free[i] != 0:
            sum_residual(i, r_out[i], d, (k + 1) % 2)

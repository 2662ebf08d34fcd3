"""Implicit (backward) Euler: per-vertex system assembly, ground contact, position update, NaN guard.

The linearised backward-Euler step solves for the new velocity v+:
``((1 + dt alpha) M + (dt^2 + dt beta) K + dt^2 K_ground + dt C_friction) v+ = M v + dt (f_el + M g + f_ground)``
where K is the warped stiffness (assembled by the FEM kernel), alpha/beta the Rayleigh coefficients.
"""

import warp as wp

# indices into the ground parameter array
GROUND_ENABLED = 0
GROUND_HEIGHT = 1
GROUND_STIFFNESS = 2
GROUND_FRICTION = 3

# a tangential speed below this (m/s) counts as sticking when the friction coefficient is computed
FRICTION_SPEED_EPS = 1.0e-3


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
    # inputs: forces and parameters
    force: wp.array(dtype=wp.vec3),
    gravity: wp.array(dtype=wp.vec3),
    up: wp.array(dtype=wp.vec3),
    ground: wp.array(dtype=float),
    dt: float,
    # outputs
    matrix_out: wp.array(dtype=wp.mat33),
    rhs_out: wp.array(dtype=wp.vec3),
    diag_inv_out: wp.array(dtype=wp.mat33),
    v_guess_out: wp.array(dtype=wp.vec3),
):
    """Adds mass, damping and ground terms to the diagonal block, builds the right-hand side and M^-1."""
    i = wp.tid()
    m = mass[i]
    vi = v[i]
    ident = wp.identity(n=3, dtype=float)
    slot = diag_slot[i]
    block = matrix_out[slot] + (1.0 + dt * alpha[i]) * m * ident
    rhs = m * vi + dt * (force[i] + m * gravity[0])

    if ground[GROUND_ENABLED] > 0.0:
        n = up[0]
        depth = ground[GROUND_HEIGHT] - wp.dot(n, x[i])
        if depth > 0.0:
            k = ground[GROUND_STIFFNESS] * m
            rhs += dt * k * depth * n
            nn = wp.outer(n, n)
            block += dt * dt * k * nn
            vt = vi - wp.dot(vi, n) * n
            c = ground[GROUND_FRICTION] * k * depth / wp.max(wp.length(vt), FRICTION_SPEED_EPS)
            block += dt * c * (ident - nn)

    matrix_out[slot] = block
    if free[i] == 0:
        rhs_out[i] = wp.vec3()
        v_guess_out[i] = wp.vec3()
        diag_inv_out[i] = wp.mat33()
    else:
        rhs_out[i] = rhs
        v_guess_out[i] = vi
        diag_inv_out[i] = wp.inverse(block)


@wp.kernel
def advance_positions(
    x: wp.array(dtype=wp.vec3),
    v_new: wp.array(dtype=wp.vec3),
    dt: float,
    x_out: wp.array(dtype=wp.vec3),
    bad_vertex_out: wp.array(dtype=wp.int32),
):
    """x+ = x + dt v+; records the lowest vertex index whose position or velocity is not finite."""
    i = wp.tid()
    vi = v_new[i]
    xi = x[i] + dt * vi
    x_out[i] = xi
    if not (wp.isfinite(xi) and wp.isfinite(vi)):
        wp.atomic_min(bad_vertex_out, 0, i)

"""Corotational linear FEM on linear tetrahedra: elastic forces and the warped stiffness blocks.

For a tet with rest shape matrix ``Dm`` (columns X1-X0, X2-X0, X3-X0) the shape-function gradients are
the rows of ``Dm^-1`` (g1, g2, g3) and ``g0 = -(g1 + g2 + g3)``. With the per-tet rotation ``R`` (polar
part of ``F = Ds Dm^-1``) the small-strain tensor in the rotated frame is ``eps = sym(R^T F) - I``, the
stress ``sigma = 2 mu eps + lambda tr(eps) I`` and the force on corner a is ``f_a = -V R sigma g_a``,
which equals ``-R K_e (R^T x - X)`` (Mueller et al. 2002). The stiffness block coupling corners a and b is
``K_ab = V (mu (g_a . g_b) I + mu g_b g_a^T + lambda g_a g_b^T)``, warped to ``R K_ab R^T``.
"""

import warp as wp

from .embedding import deformation_gradient
from .surface import add_rotated_gradients


@wp.func
def rotation_of(F: wp.mat33) -> wp.mat33:
    """Return the rotation closest to ``F`` (polar decomposition through the SVD).

    Robust for flat and inverted tets: when ``U V^T`` is a reflection, the singular direction of the
    smallest singular value is flipped, so the result is always a proper rotation.
    """
    U = wp.mat33()
    s = wp.vec3()
    V = wp.mat33()
    wp.svd3(F, U, s, V)
    R = U * wp.transpose(V)
    if wp.determinant(R) < 0.0:
        # the smallest singular value comes last in Warp's svd3
        U = wp.matrix_from_cols(U[:, 0], U[:, 1], -U[:, 2])
        R = U * wp.transpose(V)
    return R


PREDICTED_TURN_MAX = wp.constant(0.1)
"""The largest turn in one step (rad) a step is linearised ahead to (24 rad/s at 1/240 s)."""


@wp.func
def axial(M: wp.mat33) -> wp.vec3:
    """The axial vector of the skew part of ``M``: ``w`` with ``(M - M^T) / 2 = [w]x``."""
    return 0.5 * wp.vec3(M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1])


@wp.func
def turn_angle(R: wp.mat33, R_before: wp.mat33) -> float:
    """The angle (rad) of the rotation taking ``R_before`` to ``R``.

    atan2(|axis sin|, cos): accurate for small angles, where acos of the trace is not in float32.
    """
    turn = R * wp.transpose(R_before)
    return wp.atan2(wp.length(axial(turn)), 0.5 * (wp.trace(turn) - 1.0))


@wp.func
def spun(L: wp.mat33, dt: float, least: float) -> wp.mat33:
    """The rotation by ``dt`` times the spin (skew part) of the velocity gradient ``L`` (Rodrigues).

    None where that turns less than ``least`` (rad), more than :data:`PREDICTED_TURN_MAX` (a step that long is
    no free flight: a body settling in a long step would be turned past where it stops), or where the tet
    deforms faster than it spins (its strain rate, the symmetric part, is larger): a turn read off a deforming
    tet is no prediction.
    """
    w = axial(L)
    angle = wp.length(w) * dt
    D = 0.5 * (L + wp.transpose(L))
    if angle <= least or angle > PREDICTED_TURN_MAX or wp.ddot(D, D) >= 2.0 * wp.dot(w, w):
        return wp.identity(n=3, dtype=float)
    k = wp.skew(w / wp.length(w))
    return wp.identity(n=3, dtype=float) + wp.sin(angle) * k + (1.0 - wp.cos(angle)) * (k * k)


@wp.func
def shape_gradient(dm_inv: wp.mat33, a: int) -> wp.vec3:
    """Gradient of the linear shape function of corner ``a`` (0..3) in rest coordinates (1/m)."""
    if a == 0:
        return -(dm_inv[0] + dm_inv[1] + dm_inv[2])
    return dm_inv[a - 1]


@wp.func
def stiffness_block(ga: wp.vec3, gb: wp.vec3, vol: float, mu: float, lam: float) -> wp.mat33:
    """Unwarped linear-elastic stiffness block K_ab (N/m) of one tet."""
    return vol * (mu * wp.dot(ga, gb) * wp.identity(n=3, dtype=float) + mu * wp.outer(gb, ga) + lam * wp.outer(ga, gb))


@wp.kernel
def elastic_forces_and_stiffness(
    # inputs: state
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    # inputs: model
    tets: wp.array(dtype=wp.vec4i),
    dm_inv: wp.array(dtype=wp.mat33),
    rest_volume: wp.array(dtype=float),
    tet_mu: wp.array(dtype=float),
    tet_lambda: wp.array(dtype=float),
    tet_beta: wp.array(dtype=float),
    tet_slots: wp.array(dtype=wp.int32),
    rest_grad: wp.array(dtype=wp.vec3),
    # inputs: step
    dt: float,
    given_rotation: int,
    predict: int,
    predict_least: float,
    # outputs
    rotation_out: wp.array(dtype=wp.mat33),
    force_out: wp.array(dtype=wp.vec3),
    matrix_out: wp.array(dtype=wp.mat33),
    grad_out: wp.array(dtype=wp.vec3),
):
    """Per tet: rotation, corotational elastic force (N), (dt^2 + dt beta) R K_ab R^T into the upper triangle.

    The rotation is the polar part of the deformation gradient at ``x``, written to ``rotation_out``; with
    ``given_rotation`` nonzero it is read from there instead (a step linearised about rotations it chose).
    With ``predict`` nonzero the step is linearised about the rotation at ``x`` turned on for ``dt`` at the
    tet's spin (the skew part of its velocity gradient at ``v``), where it ends if it keeps spinning, when
    that turn exceeds ``predict_least`` (rad): a tet spinning steadily then needs no re-linearisation. The
    force ``-R K (R^T x - X)`` is linear in ``x`` for a fixed ``R``. With a ``grad_out`` (scenes with
    collisions; empty otherwise), also the distance gradients turned by the tet's rotation at ``x``, summed
    at its corners (see ``kernels.surface.add_rotated_gradients``).
    """
    e = wp.tid()
    t = tets[e]
    x0 = x[t[0]]
    ds = wp.matrix_from_cols(x[t[1]] - x0, x[t[2]] - x0, x[t[3]] - x0)
    dmi = dm_inv[e]
    F = ds * dmi
    R = wp.mat33()
    if given_rotation != 0:
        R = rotation_out[e]
    else:
        R_here = rotation_of(F)
        R = R_here
        if predict != 0:
            v0 = v[t[0]]
            dv = wp.matrix_from_cols(v[t[1]] - v0, v[t[2]] - v0, v[t[3]] - v0)
            R = spun(dv * wp.inverse(ds), dt, predict_least) * R_here
        rotation_out[e] = R
        if grad_out.shape[0] > 0:
            add_rotated_gradients(t, R_here, rest_grad, grad_out)

    vol = rest_volume[e]
    mu = tet_mu[e]
    lam = tet_lambda[e]
    RtF = wp.transpose(R) * F
    eps = 0.5 * (RtF + wp.transpose(RtF)) - wp.identity(n=3, dtype=float)
    sigma = 2.0 * mu * eps + lam * wp.trace(eps) * wp.identity(n=3, dtype=float)
    P = R * sigma

    scale = dt * dt + dt * tet_beta[e]
    for a in range(4):
        ga = shape_gradient(dmi, a)
        wp.atomic_add(force_out, t[a], -vol * (P * ga))
        for b in range(4):
            slot = tet_slots[e * 16 + a * 4 + b]
            if slot >= 0:  # the upper triangle only: the matrix is symmetric
                gb = shape_gradient(dmi, b)
                block = R * stiffness_block(ga, gb, vol, mu, lam) * wp.transpose(R)
                wp.atomic_add(matrix_out, slot, scale * block)


@wp.kernel
def rotation_change(
    rotation: wp.array(dtype=wp.mat33),
    rotation_before: wp.array(dtype=wp.mat33),
    tet_body: wp.array(dtype=wp.int32),
    angle_sum_out: wp.array(dtype=float),
):
    """Per body, the sum of the angles (rad) its tets turned between two rotation snapshots (atomic add)."""
    e = wp.tid()
    wp.atomic_add(angle_sum_out, tet_body[e], turn_angle(rotation[e], rotation_before[e]))


@wp.kernel
def turn_rotations(
    x: wp.array(dtype=wp.vec3),
    tets: wp.array(dtype=wp.vec4i),
    dm_inv: wp.array(dtype=wp.mat33),
    tolerance: float,
    cg_tolerance: wp.array(dtype=float),
    cg_residual: wp.array(dtype=float),
    cg_slack: float,
    rotation: wp.array(dtype=wp.mat33),
    changed_out: wp.array(dtype=wp.int32),
):
    """Replace a tet's rotation by its rotation at ``x`` where the two differ by more than ``tolerance`` (rad).

    Sets ``changed_out[0]`` to 1 where one was replaced. Does nothing once a solve stopped short of its
    tolerance (``cg_residual[0]`` above ``cg_slack`` times ``cg_tolerance[0]``; 0: a fixed iteration count):
    rotations read off an unconverged answer would steer the next solve wrong.
    """
    e = wp.tid()
    tol = cg_tolerance[0]
    if tol > 0.0 and cg_residual[0] > cg_slack * tol:
        return
    R = rotation_of(deformation_gradient(x, tets[e], dm_inv[e]))
    if turn_angle(R, rotation[e]) > tolerance:
        rotation[e] = R
        changed_out[0] = 1

"""Corotational linear FEM on linear or quadratic tetrahedra: elastic forces and the warped stiffness blocks.

For a tet with rest shape matrix ``Dm`` (columns X1-X0, X2-X0, X3-X0) the shape-function gradients are
the rows of ``Dm^-1`` (g1, g2, g3) and ``g0 = -(g1 + g2 + g3)``. With the per-tet rotation ``R`` (polar
part of ``F = Ds Dm^-1``) the small-strain tensor in the rotated frame is ``eps = sym(R^T F) - I``, the
stress ``sigma = 2 mu eps + lambda tr(eps) I`` and the force on corner a is ``f_a = -V R sigma g_a``,
which equals ``-R K_e (R^T x - X)`` (Mueller et al. 2002). The stiffness block coupling corners a and b is
``K_ab = V (mu (g_a . g_b) I + mu g_b g_a^T + lambda g_a g_b^T)``, warped to ``R K_ab R^T``. A quadratic tet
(corners and edge midpoints) takes the same rotation from its corners and integrates its strain, linear
over the tet, at four points.
"""

import warp as wp

from .embedding import deformation_gradient
from .grid import warp_sum_at
from .surface import add_rotated_gradients

wp.set_module_options({"max_unroll": 4, "enable_backward": False})
"""Unroll the four corners' and four quadrature points' loops, not the ten nodes' (fully unrolled, a quadratic
tet's 10 x 10 x 4 blocks take minutes to compile); nothing here is differentiated."""


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


@wp.func
def edge_matrix(x: wp.array(dtype=wp.vec3), t: wp.vec4i) -> wp.mat33:
    """``Ds``: the edges from corner 0 to corners 1-3 of the tet with corners ``t`` at ``x``, as columns (m)."""
    o = x[t[0]]
    return wp.matrix_from_cols(x[t[1]] - o, x[t[2]] - o, x[t[3]] - o)


@wp.func
def rotated_stress(R: wp.mat33, F: wp.mat33, mu: float, lam: float) -> wp.mat33:
    """``R sigma`` (Pa): the linear stress of the strain ``sym(R^T F) - I`` in the frame turned by ``R``."""
    RtF = wp.transpose(R) * F
    ident = wp.identity(n=3, dtype=float)
    eps = 0.5 * (RtF + wp.transpose(RtF)) - ident
    return R * (2.0 * mu * eps + lam * wp.trace(eps) * ident)


@wp.func
def step_rotation(
    ds: wp.mat33,
    F: wp.mat33,
    v: wp.array(dtype=wp.vec3),
    t: wp.vec4i,
    e: int,
    dt: float,
    given_rotation: int,
    predict: int,
    predict_least: float,
    rest_grad: wp.array(dtype=wp.vec3),
    rotation_out: wp.array(dtype=wp.mat33),
    grad_out: wp.array(dtype=wp.vec3),
) -> wp.mat33:
    """The rotation tet ``e`` (corners ``t``, edge matrix ``ds``, deformation gradient ``F``) is linearised about.

    See :func:`elastic_forces_and_stiffness`: read from ``rotation_out`` with ``given_rotation``, else the polar
    part of ``F``, predicted on by the tet's spin with ``predict``, written to ``rotation_out``; the distance
    gradients turned by the rotation at the tet's positions are added to ``grad_out`` where it is not empty.
    """
    if given_rotation != 0:
        return rotation_out[e]
    R_here = rotation_of(F)
    R = R_here
    if predict != 0:
        v0 = v[t[0]]
        dv = wp.matrix_from_cols(v[t[1]] - v0, v[t[2]] - v0, v[t[3]] - v0)
        R = spun(dv * wp.inverse(ds), dt, predict_least) * R_here
    rotation_out[e] = R
    if grad_out.shape[0] > 0:
        add_rotated_gradients(t, R_here, rest_grad, grad_out)
    return R


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
    dmi = dm_inv[e]
    ds = edge_matrix(x, t)
    F = ds * dmi
    R = step_rotation(ds, F, v, t, e, dt, given_rotation, predict, predict_least, rest_grad, rotation_out, grad_out)

    vol = rest_volume[e]
    mu = tet_mu[e]
    lam = tet_lambda[e]
    P = rotated_stress(R, F, mu, lam)

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


vec6i = wp.types.vector(length=6, dtype=wp.int32)
"""A quadratic tet's edge nodes, on its edges (0,1), (0,2), (0,3), (1,2), (1,3), (2,3) in that order."""

QUAD_A = wp.constant(0.5854101966249685)
QUAD_B = wp.constant(0.1381966011250105)
"""The four-point rule on a tet (exact to degree 2, weights V/4): point q has barycentric coordinate
``QUAD_A`` at corner q and ``QUAD_B`` at the others."""


@wp.func
def edge_ends(k: int) -> wp.vec2i:
    """The corners of edge ``k`` (0..5) of a tet, in :data:`vec6i`'s order."""
    if k < 3:
        return wp.vec2i(0, k + 1)
    if k < 5:
        return wp.vec2i(1, k - 1)
    return wp.vec2i(2, 3)


@wp.func
def quadratic_gradient(dmi: wp.mat33, node: int, q: int) -> wp.vec3:
    """Rest gradient (1/m) of the quadratic shape function of ``node`` (0-3 corners, 4-9 edges) at point ``q``.

    Corner c: ``(4 l_c - 1) g_c``; edge (i, j): ``4 (l_i g_j + l_j g_i)``, with ``l`` the point's barycentric
    coordinates and ``g`` the linear shape functions' gradients.
    """
    if node < 4:
        lc = wp.where(node == q, QUAD_A, QUAD_B)
        return (4.0 * lc - 1.0) * shape_gradient(dmi, node)
    ends = edge_ends(node - 4)
    li = wp.where(ends[0] == q, QUAD_A, QUAD_B)
    lj = wp.where(ends[1] == q, QUAD_A, QUAD_B)
    return 4.0 * (li * shape_gradient(dmi, ends[1]) + lj * shape_gradient(dmi, ends[0]))


@wp.func
def quadratic_node(t: wp.vec4i, edges: vec6i, node: int) -> int:
    """Global index of local node ``node`` (0-3 the corners ``t``, 4-9 the ``edges``)."""
    if node < 4:
        return t[node]
    return edges[node - 4]


@wp.func
def point_stress(
    x: wp.array(dtype=wp.vec3), t: wp.vec4i, edges: vec6i, dmi: wp.mat33, R: wp.mat33, mu: float, lam: float, q: int
) -> wp.mat33:
    """``R sigma`` (Pa) at quadrature point ``q`` of a quadratic tet: the stress of ``sym(R^T F_q) - I``.

    ``F_q`` sums the nodes' positions relative to corner 0 (the gradients sum to zero): absolute positions
    would lose the float32 digits a small strain lives in.
    """
    x0 = x[t[0]]
    Fq = wp.mat33()
    for n in range(1, 10):
        Fq += wp.outer(x[quadratic_node(t, edges, n)] - x0, quadratic_gradient(dmi, n, q))
    return rotated_stress(R, Fq, mu, lam)


@wp.kernel
def quadratic_forces_and_stiffness(
    # inputs: state
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    # inputs: model
    tets: wp.array(dtype=wp.vec4i),
    tet_edges: wp.array(dtype=vec6i),
    dm_inv: wp.array(dtype=wp.mat33),
    rest_volume: wp.array(dtype=float),
    tet_mu: wp.array(dtype=float),
    tet_lambda: wp.array(dtype=float),
    tet_beta: wp.array(dtype=float),
    node_slots: wp.array(dtype=wp.int32),
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
    """:func:`elastic_forces_and_stiffness` for quadratic (10-node) tets.

    One rotation per tet, that of its corners (as for a linear tet); the strain ``sym(R^T F_q) - I`` at each
    of four quadrature points, ``F_q = sum_n x_n grad N_n(q)``; force ``f_n = -V/4 sum_q R sigma_q grad N_n(q)``
    and blocks ``K_ab = V/4 sum_q K(grad N_a(q), grad N_b(q))``, warped and stored at ``node_slots[e*100 + a*10
    + b]`` (-1 below the diagonal).
    """
    e = wp.tid()
    t = tets[e]
    edges = tet_edges[e]
    dmi = dm_inv[e]
    ds = edge_matrix(x, t)
    R = step_rotation(
        ds, ds * dmi, v, t, e, dt, given_rotation, predict, predict_least, rest_grad, rotation_out, grad_out
    )
    w = 0.25 * rest_volume[e]
    mu = tet_mu[e]
    lam = tet_lambda[e]

    P0 = point_stress(x, t, edges, dmi, R, mu, lam, 0)
    P1 = point_stress(x, t, edges, dmi, R, mu, lam, 1)
    P2 = point_stress(x, t, edges, dmi, R, mu, lam, 2)
    P3 = point_stress(x, t, edges, dmi, R, mu, lam, 3)
    for n in range(10):
        f = P0 * quadratic_gradient(dmi, n, 0) + P1 * quadratic_gradient(dmi, n, 1)
        f += P2 * quadratic_gradient(dmi, n, 2) + P3 * quadratic_gradient(dmi, n, 3)
        wp.atomic_add(force_out, quadratic_node(t, edges, n), -w * f)

    scale = dt * dt + dt * tet_beta[e]
    for a in range(10):
        for b in range(10):
            slot = node_slots[e * 100 + a * 10 + b]
            if slot >= 0:
                K = wp.mat33()
                for q in range(4):
                    K += stiffness_block(quadratic_gradient(dmi, a, q), quadratic_gradient(dmi, b, q), w, mu, lam)
                wp.atomic_add(matrix_out, slot, scale * (R * K * wp.transpose(R)))


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
    rest_volume: wp.array(dtype=float),
    tet_body: wp.array(dtype=wp.int32),
    rotation: wp.array(dtype=wp.mat33),
    cg_tolerance: wp.array(dtype=float),
    cg_residual: wp.array(dtype=float),
    cg_slack: float,
    tolerance: float,
    turned_out: wp.array(dtype=wp.mat33),
    turn_out: wp.array(dtype=float),
    body_turn_out: wp.array(dtype=wp.vec3),
):
    """Each tet's rotation at ``x`` and its turn (rad) from ``rotation``; per body, how much its tets turned.

    ``body_turn_out[body]`` (zeroed first; one atomic per warp) receives the sum of volume x turn^4 and the count
    of tets that turned more than twice ``tolerance`` (rad), in its first two components. Nothing is measured, and
    the turns read 0, once a solve stopped short of its tolerance (``cg_residual[0]`` above ``cg_slack`` times
    ``cg_tolerance[0]``; 0: a fixed iteration count): rotations read off an unconverged answer would steer the
    next solve wrong.
    """
    e = wp.tid()
    tol = cg_tolerance[0]
    turn = float(0.0)
    if not (tol > 0.0 and cg_residual[0] > cg_slack * tol):
        R = rotation_of(deformation_gradient(x, tets[e], dm_inv[e]))
        turn = turn_angle(R, rotation[e])
        turned_out[e] = R
    turn_out[e] = turn
    turn2 = turn * turn
    far = wp.where(turn > 2.0 * tolerance, 1.0, 0.0)
    warp_sum_at(wp.vec3(rest_volume[e] * turn2 * turn2, far, 0.0), tet_body[e], body_turn_out)


@wp.kernel
def replace_turned(
    turned: wp.array(dtype=wp.mat33),
    turn: wp.array(dtype=float),
    tet_body: wp.array(dtype=wp.int32),
    body_turn: wp.array(dtype=wp.vec3),
    body_volume: wp.array(dtype=float),
    tolerance: float,
    rotation: wp.array(dtype=wp.mat33),
    changed_out: wp.array(dtype=wp.int32),
    body_changed_out: wp.array(dtype=wp.int32),
):
    """Re-linearise the tets past ``tolerance`` (rad) in the bodies that turned enough.

    In each body whose volume average of turn^4 exceeds ``tolerance``^4, or one of whose tets turned more than
    twice ``tolerance``, the tets that turned more than ``tolerance`` take their rotation at the step's end;
    ``changed_out[0]`` becomes 1 where one did, and ``body_changed_out`` of its body.
    """
    e = wp.tid()
    b = tet_body[e]
    tol2 = tolerance * tolerance
    enough = body_turn[b][0] > tol2 * tol2 * body_volume[b] or body_turn[b][1] > 0.0
    if turn[e] > tolerance and enough:
        rotation[e] = turned[e]
        changed_out[0] = 1
        body_changed_out[b] = 1

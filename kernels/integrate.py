"""Implicit (backward) Euler: per-vertex system assembly, static colliders, position update, NaN guard.

The linearised backward-Euler step solves for the new velocity v+:
``((1 + dt alpha) M + (dt^2 + dt beta) K + dt^2 K_c + dt C_friction) v+ = M v + dt (f_el + M g + f_c)``
where K is the warped stiffness (assembled by the FEM kernel), alpha/beta the Rayleigh coefficients and
K_c, C_friction, f_c the static colliders' penalty and friction (the ground is a plane collider), on the
tet vertices and on the skin (the dense vertices outside the tets, whose terms reach the tet's corners).
A collider may move rigidly (:mod:`warpfem.kernels.drive` poses it each step): its contacts then hold the
points' velocity relative to its own surface's.
"""

import warp as wp

from .embedding import interpolate
from .grid import warp_max_at, warp_sum_at
from .rigid import mark_pair

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated

# static collider kinds
PLANE = wp.constant(0)
SPHERE = wp.constant(1)
BOX = wp.constant(2)
MESH = wp.constant(3)

# the distance (m) of a point no mesh face is near
FAR = 1.0e30

# a tangential speed below this (m/s) counts as sticking when the friction coefficient is computed
FRICTION_SPEED_EPS = 1.0e-3

FRICTION_TIE_RATIO = 4.0
"""The most a body-body contact's implicit friction may stiffen its tangential coupling, relative to the
penalty's normal stiffness (see :func:`tie_friction`). Chosen by measurement (docs/decisions.md, "Friction
ties between bodies")."""


@wp.func
def tie_friction(mu: float, a: float, depth: float, slip: float, dt: float):
    """Implicit friction coefficient c (N s/m) of a body-body contact.

    ``c = mu a d / max(slip, eps, mu d / (r dt))`` for penalty stiffness ``a`` (N/m), depth ``d`` (m),
    tangential slip speed (m/s), ``eps`` :data:`FRICTION_SPEED_EPS` and ``r`` :data:`FRICTION_TIE_RATIO`.
    Below the larger of the two speeds the contact sticks, its tangential term ``dt c`` at most r times the
    normal ``dt^2 a``: sticking contacts otherwise tie two moving bodies hundreds of times more stiffly than
    the normal penalty, which block-Jacobi CG cannot precondition (a soft body resting on a stiff one stopped
    at the CG cap in most steps). Static colliders (:func:`static_contact`) keep the plain rule: their tie
    is diagonal, which Jacobi inverts exactly.
    """
    d = wp.max(depth, 0.0)
    stick = wp.max(FRICTION_SPEED_EPS, mu * d / (FRICTION_TIE_RATIO * dt))
    return mu * a * d / wp.max(slip, stick)


@wp.struct
class Colliders:
    """The static colliders, one entry each, posed at the start of the step and at its end.

    ``center`` and ``rotation`` place the collider's own frame in the world at the step's start (a plane:
    a point on it and the identity; a sphere or box: its centre and orientation; a mesh: its vertices'
    frame), ``center_next`` and ``rotation_next`` at the step's end (the same for a collider that does not
    move, ``moving`` 0). ``size``: a plane's normal, a sphere's radius, a box's half extents, a mesh's query
    radius (m, in ``size[0]``: as far as it acts behind its surface). ``response``: penalty per unit mass
    (1/s^2), friction, and the offset: how far above its surface the penalty starts, as a share of the
    touching body's size (``body_size``, m). ``mesh``: the ``wp.Mesh`` id of a mesh collider (0 for the others).
    ``open_edges[face_start[o] + f]``: which edges of the mesh's face f bound an open mesh (bit 0: corners
    0-1, bit 1: 1-2, bit 2: 2-0) and which of its corners lie on such an edge (bits 3-5: corners 0-2).
    ``gravity[0]``: the scene's gravity (m/s^2), which the speculative contact test adds to a point's motion.
    """

    kind: wp.array(dtype=wp.int32)
    center: wp.array(dtype=wp.vec3)
    rotation: wp.array(dtype=wp.quat)
    center_next: wp.array(dtype=wp.vec3)
    rotation_next: wp.array(dtype=wp.quat)
    moving: wp.array(dtype=wp.int32)
    size: wp.array(dtype=wp.vec3)
    response: wp.array(dtype=wp.vec3)
    body_size: wp.array(dtype=float)
    mesh: wp.array(dtype=wp.uint64)
    face_start: wp.array(dtype=wp.int32)
    open_edges: wp.array(dtype=wp.int32)
    gravity: wp.array(dtype=wp.vec3)


@wp.func
def on_open_edge(open_edges: wp.array(dtype=wp.int32), face: int, u: float, v: float) -> bool:
    """Whether the point of barycentrics (u, v, w = 1 - u - v) of a face lies on an open edge of the mesh.

    On one of the face's own edges flagged open (bits 0-2), or at one of its corners on an open edge (bits 3-5).
    """
    flags = open_edges[face]
    eps = 1.0e-5
    w = 1.0 - u - v
    edge = ((flags & 1) != 0 and w < eps) or ((flags & 2) != 0 and u < eps) or ((flags & 4) != 0 and v < eps)
    corner = (
        ((flags & 8) != 0 and v < eps and w < eps)
        or ((flags & 16) != 0 and u < eps and w < eps)
        or ((flags & 32) != 0 and u < eps and v < eps)
    )
    return edge or corner


@wp.func
def solid_distance(c: Colliders, o: int, d: wp.vec3) -> wp.vec4:
    """:func:`shape_distance` for a plane, a sphere or a box: a few operations, none of a mesh query's registers.

    Plane: normal ``size`` through the origin. Sphere: radius ``size[0]``. Box: half extents ``size``.
    """
    kind = c.kind[o]
    size = c.size[o]
    if kind == PLANE:
        return wp.vec4(wp.dot(size, d), size[0], size[1], size[2])
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
def shape_distance(c: Colliders, o: int, d: wp.vec3) -> wp.vec4:
    """Signed distance (m, negative inside) of ``d`` (in collider ``o``'s own frame) and its outward unit normal.

    Mesh: the nearest point of the mesh within ``size[0]``, inside where its angle-weighted normal says (behind
    an open mesh's faces, but not past its open edges); none within reach reads as far outside. The other
    kinds: :func:`solid_distance`.
    """
    if c.kind[o] == MESH:
        size = c.size[o]
        mesh = c.mesh[o]
        query = wp.mesh_query_point_sign_normal(mesh, d, size[0])
        if not query.result:  # farther than the mesh acts: never in contact, not even speculatively
            return wp.vec4(FAR, 0.0, 1.0, 0.0)
        off = d - wp.mesh_eval_position(mesh, query.face, query.u, query.v)
        dist = wp.length(off)
        sign = query.sign
        if sign < 0.0 and on_open_edge(c.open_edges, c.face_start[o] + query.face, query.u, query.v):
            sign = 1.0  # past an open mesh's edge: beside it, not behind it
        n = wp.mesh_eval_face_normal(mesh, query.face)
        w = 1.0 - query.u - query.v
        inner = wp.min(wp.min(query.u, query.v), w) > 1.0e-5  # off is along the face's normal: take it exact
        if not inner and dist > 1.0e-3 * size[0]:  # clear of an edge or corner: away from it (else rounding)
            n = off * (sign / dist)
        return wp.vec4(sign * dist, n[0], n[1], n[2])
    return solid_distance(c, o, d)


@wp.func
def collider_distance(c: Colliders, o: int, p: wp.vec3) -> wp.vec4:
    """Signed distance (m, negative inside) of world point ``p`` to collider ``o`` at the step's start, and normal.

    The outward unit normal is in world axes.
    """
    q = c.rotation[o]
    dn = shape_distance(c, o, wp.quat_rotate_inv(q, p - c.center[o]))
    n = wp.quat_rotate(q, wp.vec3(dn[1], dn[2], dn[3]))
    return wp.vec4(dn[0], n[0], n[1], n[2])


@wp.func
def collider_velocity(c: Colliders, o: int, p: wp.vec3, dt: float) -> wp.vec3:
    """The velocity (m/s) over the step of collider ``o``'s surface point at ``p``: zero where it does not move."""
    if c.moving[o] == 0:
        return wp.vec3()
    local = wp.quat_rotate_inv(c.rotation[o], p - c.center[o])
    return (wp.quat_rotate(c.rotation_next[o], local) + c.center_next[o] - p) / dt


@wp.func
def offset_depth(c: Colliders, o: int, distance: float, body: int) -> float:
    """Depth (m) of a point of ``body`` at signed ``distance`` from collider ``o``'s surface, below its offset.

    The penalty starts the offset (a share of the body's size) above the surface, so the give a penalty
    needs to hold a load is spent in that gap rather than below the visible surface.
    """
    return c.response[o][2] * c.body_size[body] - distance


@wp.func
def lands(depth: float, n: wp.vec3, v: wp.vec3, g: wp.vec3, dt: float) -> bool:
    """Whether a point ``depth`` below a collider's surface (normal ``n``), moving at ``v``, ends the step below it.

    The speculative contact test. A point on or below the surface also falls under gravity ``g`` meanwhile: it
    stays in contact unless it leaves faster than gravity brings it back within the step. A point released
    as soon as it leaves flies on at the speed the penalty pushed it out with, falls back a step later and is
    pushed out again: a bounce a stiff body at long steps never leaves (docs/decisions.md, "Resting contacts
    under gravity").
    """
    fall = wp.where(depth >= 0.0, dt * g, wp.vec3(0.0))
    return depth - dt * wp.dot(n, v + fall) > 0.0


@wp.func
def within_step(depth: float, n: wp.vec3, vp: wp.vec3, v_body: wp.vec3, g: wp.vec3, dt: float) -> bool:
    """Whether a point ``depth`` below a collider's surface (normal ``n``) acts with it this step.

    It :func:`lands` at its own speed or at its body's, which drags it along.
    """
    return lands(depth, n, vp, g, dt) or lands(depth, n, v_body, g, dt)


@wp.func
def contact_from(
    c: Colliders, o: int, dn: wp.vec4, vc: wp.vec3, vp: wp.vec3, v_body: wp.vec3, m: float, body: int, dt: float
):
    """Collider ``o``'s penalty force and matrix term on a point of mass ``m`` of body ``body`` (zero if none).

    ``dn``: the point's :func:`collider_distance`; ``vc``: :func:`collider_velocity` there.

    The collider (stiffness k per unit mass and friction mu in its ``response``) acts on a point that ends the
    step below its surface at its own speed or at its body's, which drags it along, relative to the surface's
    own speed v_c (speculative contact, :func:`lands`): the penalty k m (depth + dt n.v_c) n and
    dt^2 k m n n^T in the matrix, which hold the depth the step ends at (above the surface only the velocity
    terms act: they damp the approach and never attract), and implicit friction dt c (I - n n^T) towards the
    surface's tangential speed, c = mu k m depth / |v_t|. The depth counts from the collider's offset above its
    surface (:func:`offset_depth`).
    """
    n = wp.vec3(dn[1], dn[2], dn[3])
    depth = offset_depth(c, o, dn[0], body)
    force = wp.vec3()
    block = wp.mat33()
    if within_step(depth, n, vp - vc, v_body - vc, c.gravity[0], dt):
        response = c.response[o]
        k = response[0] * m
        pen = wp.max(depth, 0.0)
        nn = wp.outer(n, n)
        tangent = wp.identity(n=3, dtype=float) - nn
        vt = tangent * (vp - vc)
        friction = response[1] * k * pen / wp.max(wp.length(vt), FRICTION_SPEED_EPS)
        force = k * (pen + dt * wp.dot(n, vc)) * n + friction * (tangent * vc)
        block = dt * dt * k * nn + dt * friction * tangent
    return force, block


@wp.func
def static_contact(c: Colliders, o: int, p: wp.vec3, vp: wp.vec3, v_body: wp.vec3, m: float, body: int, dt: float):
    """Collider ``o``'s penalty force and matrix term on a point at ``p`` (:func:`contact_from`)."""
    return contact_from(c, o, collider_distance(c, o, p), collider_velocity(c, o, p, dt), vp, v_body, m, body, dt)


@wp.kernel
def clear_step(
    force: wp.array(dtype=wp.vec3),
    grad: wp.array(dtype=wp.vec3),
    momentum: wp.array(dtype=wp.vec3),
    matrix: wp.array(dtype=wp.mat33),
    point_contact: wp.array(dtype=wp.int32),
    late_vertex: wp.array(dtype=wp.int32),
    late_skin: wp.array(dtype=wp.int32),
    contact_counts: wp.array(dtype=wp.int32),
    flags: wp.array(dtype=wp.int32),
    body_speed: wp.array(dtype=float),
):
    """Zero every array a step accumulates into or counts in: one launch instead of a memset each."""
    i = wp.tid()
    if i < force.shape[0]:
        force[i] = wp.vec3(0.0)
    if i < grad.shape[0]:
        grad[i] = wp.vec3(0.0)
    if i < momentum.shape[0]:
        momentum[i] = wp.vec3(0.0)
    if i < matrix.shape[0]:
        matrix[i] = wp.mat33(0.0)
    if i < point_contact.shape[0]:
        point_contact[i] = 0
    if i < late_vertex.shape[0]:
        late_vertex[i] = 0
    if i < late_skin.shape[0]:
        late_skin[i] = 0
    if i < contact_counts.shape[0]:
        contact_counts[i] = 0
    if i < flags.shape[0]:
        flags[i] = 0
    if i < body_speed.shape[0]:
        body_speed[i] = 0.0


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
    elastic_force: wp.array(dtype=wp.vec3),
    gravity: wp.array(dtype=wp.vec3),
    colliders: Colliders,
    held_v: wp.array(dtype=wp.vec3),
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
    rhs_base_out: wp.array(dtype=wp.vec3),
):
    """Adds mass, damping and static-collider terms to the diagonal block, builds the right-hand side and M^-1.

    The elastic force is ``force`` plus ``elastic_force`` where that is not empty; then ``rhs_base_out``
    receives the right-hand side without it (what a step re-linearised about other rotations keeps), and the
    free rows' inverse diagonal blocks are left to be taken once the elastic blocks are added.

    Each static collider acts on the vertex as :func:`static_contact` says: its force on the right-hand side,
    its matrix term in the diagonal block; not on a vertex outside the visible surface (a corner of the cage
    around a dense surface, whose samples meet the colliders instead). A held vertex (``free`` 0) leaves the
    solve with the velocity ``held_v`` gives it (a handle's motion; zero, or ``held_v`` empty, for a pin).
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
        for o in range(colliders.kind.shape[0]):
            f, s = static_contact(colliders, o, xi, vi, v_body, m, b, dt)
            rhs += dt * f
            block += s

    matrix_out[slot] = block
    if rhs_base_out.shape[0] > 0:
        rhs_base_out[i] = wp.where(free[i] == 0, wp.vec3(), rhs)
        rhs += dt * elastic_force[i]
    if free[i] == 0:
        rhs_out[i] = wp.vec3()
        v_guess_out[i] = wp.vec3()
        if held_v.shape[0] > 0:
            v_guess_out[i] = held_v[i]
        direction_out[i] = wp.vec3()
        diag_inv_out[i] = wp.mat33()
    else:
        rhs_out[i] = rhs
        v_guess_out[i] = vi
        d = dv[i]
        direction_out[i] = wp.where(wp.isfinite(d), d, wp.vec3())  # a blown-up step must not poison the next
        if rhs_base_out.shape[0] == 0:  # else the block lacks the elastic part: inverted once that is added
            diag_inv_out[i] = wp.inverse(block)


@wp.func
def add_symmetric(
    matrix_out: wp.array(dtype=wp.mat33),
    cell_slots: wp.array(dtype=wp.int32),
    e: int,
    w: wp.vec4,
    block: wp.mat33,
):
    """Add ``w_a w_b block`` to every stored block (a, b) of cell ``e`` (a symmetric term of one embedded point)."""
    for a in range(4):
        for b in range(4):
            slot = cell_slots[e * 16 + a * 4 + b]
            if slot >= 0:
                wp.atomic_add(matrix_out, slot, (w[a] * w[b]) * block)


@wp.func
def late_contact(
    c: Colliders, o: int, p: wp.vec3, vp: wp.vec3, vp_new: wp.vec3, v_body: wp.vec3, m: float, body: int, dt: float
):
    """A static contact the step's first solve would cross without having counted it (zero force and block if none).

    A point that :func:`static_contact` left free (not within one step of the surface at the step's start
    speeds) but whose new velocity carries it below the surface by the step's end (relative to the surface's
    own speed v_c): it gets the penalty's matrix term ``dt^2 k m n n^T`` and the force
    ``k m (depth + dt n.v_c) n`` at its (negative) start depth, so the second solve brings it to the surface
    by the step's end instead of through it.
    """
    dn = collider_distance(c, o, p)
    n = wp.vec3(dn[1], dn[2], dn[3])
    depth = offset_depth(c, o, dn[0], body)
    force = wp.vec3()
    block = wp.mat33()
    vc = collider_velocity(c, o, p, dt)
    crosses = depth - dt * wp.dot(n, vp_new - vc) > 0.0
    if crosses and not within_step(depth, n, vp - vc, v_body - vc, c.gravity[0], dt):
        k = c.response[o][0] * m
        force = k * (depth + dt * wp.dot(n, vc)) * n
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
    colliders: Colliders,
    vertex_body: wp.array(dtype=wp.int32),
    body_momentum: wp.array(dtype=wp.vec3),
    body_mass: wp.array(dtype=float),
    dt: float,
    late_out: wp.array(dtype=wp.int32),
    count_out: wp.array(dtype=wp.int32),
    matrix_out: wp.array(dtype=wp.mat33),
    rhs_out: wp.array(dtype=wp.vec3),
    matrix_base_out: wp.array(dtype=wp.mat33),
    rhs_base_out: wp.array(dtype=wp.vec3),
    body_speed_out: wp.array(dtype=float),
):
    """:func:`late_contact` on each free tet vertex inside the visible surface not yet given one this step.

    Adds to its right-hand side and diagonal block (and to the system without elasticity, where
    ``rhs_base_out`` is not empty), marks it in ``late_out`` and counts it in ``count_out[0]``. Every vertex's
    speed in ``v_new`` goes into its body's maximum in ``body_speed_out`` (where not empty).
    """
    i = wp.tid()
    if body_speed_out.shape[0] > 0:
        warp_max_at(wp.length(v_new[i]), vertex_body[i], body_speed_out)
    if free[i] == 0 or vertex_depth[i] < 0.0 or late_out[i] != 0:
        return
    b = vertex_body[i]
    v_body = body_momentum[b] / body_mass[b]
    for o in range(colliders.kind.shape[0]):
        f, s = late_contact(colliders, o, x[i], v[i], v_new[i], v_body, mass[i], b, dt)
        if wp.trace(s) > 0.0:
            rhs_out[i] = rhs_out[i] + dt * f
            matrix_out[diag_slot[i]] = matrix_out[diag_slot[i]] + s
            if rhs_base_out.shape[0] > 0:
                rhs_base_out[i] = rhs_base_out[i] + dt * f
                matrix_base_out[diag_slot[i]] = matrix_base_out[diag_slot[i]] + s
            late_out[i] = 1
            wp.atomic_add(count_out, 0, 1)


LIFT_GIVE = wp.constant(1.0e-4)
"""How far (a share of the body's size) a point may lie below a still collider before :func:`lift_points` moves
it: the penalty holds a resting point a little below the surface where the collider's offset is 0, and lifting
that depth out every step, against the penalty, kept a soft body moving."""


@wp.func
def lift_from(
    dn: wp.vec4,
    give: float,
    t: wp.vec4i,
    w: wp.vec4,
    free: wp.array(dtype=wp.int32),
    up_out: wp.array(dtype=wp.vec3),
    down_out: wp.array(dtype=wp.vec3),
):
    """The moves a point at :func:`collider_distance` ``dn`` asks of its cell's nodes (see :func:`lift_points`)."""
    if dn[0] < -give:
        move = (-dn[0] - give) * wp.vec3(dn[1], dn[2], dn[3])
        for c in range(4):
            if w[c] > 0.0 and free[t[c]] != 0:
                wp.atomic_max(up_out, t[c], move)
                wp.atomic_min(down_out, t[c], move)


@wp.kernel
def lift_points(
    x: wp.array(dtype=wp.vec3),
    cells: wp.array(dtype=wp.vec4i),
    cell_body: wp.array(dtype=wp.int32),
    free: wp.array(dtype=wp.int32),
    point_cell: wp.array(dtype=wp.int32),
    point_bary: wp.array(dtype=wp.vec4),
    colliders: Colliders,
    up_out: wp.array(dtype=wp.vec3),
    down_out: wp.array(dtype=wp.vec3),
):
    """How far each free node must move so that no embedded point lies below a still collider's surface.

    Below it by more than :data:`LIFT_GIVE` of its body's size, that is: a point (skin point or dense vertex,
    at weights ``point_bary`` in cell ``point_cell``) at depth ``d`` past that give below a collider that does
    not move (normal ``n``) asks each free node of its cell with a positive weight to move by ``d n``: moved
    so, the nodes carry the point up by at least ``d``. A node takes the largest such move per axis, the
    positive parts in ``up_out`` and the negative in ``down_out`` (both zero where none asks;
    :func:`apply_lift` zeroes them again). The planes, spheres and boxes: :func:`lift_points_meshes` holds the
    meshes' query, and its registers, apart.
    """
    i = wp.tid()
    e = point_cell[i]
    t = cells[e]
    w = point_bary[i]
    p = interpolate(x, t, w)
    give = LIFT_GIVE * colliders.body_size[cell_body[e]]
    for o in range(colliders.kind.shape[0]):
        if colliders.moving[o] == 0 and colliders.kind[o] != MESH:
            q = colliders.rotation[o]
            dn = solid_distance(colliders, o, wp.quat_rotate_inv(q, p - colliders.center[o]))
            n = wp.quat_rotate(q, wp.vec3(dn[1], dn[2], dn[3]))
            lift_from(wp.vec4(dn[0], n[0], n[1], n[2]), give, t, w, free, up_out, down_out)


@wp.kernel
def lift_points_meshes(
    x: wp.array(dtype=wp.vec3),
    cells: wp.array(dtype=wp.vec4i),
    cell_body: wp.array(dtype=wp.int32),
    free: wp.array(dtype=wp.int32),
    point_cell: wp.array(dtype=wp.int32),
    point_bary: wp.array(dtype=wp.vec4),
    colliders: Colliders,
    up_out: wp.array(dtype=wp.vec3),
    down_out: wp.array(dtype=wp.vec3),
):
    """:func:`lift_points` for the still mesh colliders."""
    i = wp.tid()
    e = point_cell[i]
    t = cells[e]
    w = point_bary[i]
    p = interpolate(x, t, w)
    give = LIFT_GIVE * colliders.body_size[cell_body[e]]
    for o in range(colliders.kind.shape[0]):
        if colliders.moving[o] == 0 and colliders.kind[o] == MESH:
            lift_from(collider_distance(colliders, o, p), give, t, w, free, up_out, down_out)


@wp.kernel
def apply_lift(
    up: wp.array(dtype=wp.vec3),
    down: wp.array(dtype=wp.vec3),
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
    dv_out: wp.array(dtype=wp.vec3),
):
    """Move each node by what :func:`lift_points` asked and stop its velocity along that move where it went against it.

    The velocity change goes into ``dv_out`` too (the next step's CG start moves along it); the requests are
    zeroed for the next step.
    """
    i = wp.tid()
    move = up[i] + down[i]
    if wp.length_sq(move) == 0.0:
        return
    x_out[i] = x_out[i] + move
    n = wp.normalize(move)
    vn = wp.dot(v_out[i], n)
    if vn < 0.0:
        v_out[i] = v_out[i] - vn * n
        dv_out[i] = dv_out[i] - vn * n
    up[i] = wp.vec3()
    down[i] = wp.vec3()


@wp.kernel
def add_elastic(
    free: wp.array(dtype=wp.int32),
    matrix_base: wp.array(dtype=wp.mat33),
    rhs_base: wp.array(dtype=wp.vec3),
    dt: float,
    elastic_matrix: wp.array(dtype=wp.mat33),
    elastic_force: wp.array(dtype=wp.vec3),
    matrix_out: wp.array(dtype=wp.mat33),
    rhs_out: wp.array(dtype=wp.vec3),
):
    """The system from its base and its elastic part, each elastic entry zeroed once read.

    ``matrix_out = matrix_base + elastic_matrix`` block by block and ``rhs_out = rhs_base + dt elastic_force``
    (zero on held vertices); the next assembly adds into the zeros. One thread per block, its first threads
    also a vertex each.
    """
    s = wp.tid()
    if s < matrix_out.shape[0]:
        matrix_out[s] = matrix_base[s] + elastic_matrix[s]
        elastic_matrix[s] = wp.mat33()
    if s < rhs_out.shape[0]:
        rhs_out[s] = wp.where(free[s] == 0, wp.vec3(), rhs_base[s] + dt * elastic_force[s])
        elastic_force[s] = wp.vec3()


@wp.kernel
def moving_bodies(
    late_vertex: wp.array(dtype=wp.int32),
    vertex_body: wp.array(dtype=wp.int32),
    late_skin: wp.array(dtype=wp.int32),
    skin_cell: wp.array(dtype=wp.int32),
    cell_body: wp.array(dtype=wp.int32),
    pair_count: wp.array(dtype=wp.int32),
    verts_a: wp.array(dtype=wp.vec4i),
    verts_b: wp.array(dtype=wp.vec4i),
    moving_out: wp.array(dtype=wp.int32),
):
    """Marks the bodies an extra solve of the step moves.

    Each a late static contact touched (a marked vertex or skin point), and both bodies of each live contact
    pair between bodies (the coupling's, as ``kernels.rigid.mark_touched_pairs`` marks them).

    A body that touches no other keeps its answer unless it is marked for another reason (a late contact, a
    rotation update); the others move, since theirs is tied to their neighbours' through the contacts.
    """
    i = wp.tid()
    if i < late_vertex.shape[0]:
        if late_vertex[i] != 0:
            moving_out[vertex_body[i]] = 1
    if i < late_skin.shape[0]:
        if late_skin[i] != 0:
            moving_out[cell_body[skin_cell[i]]] = 1
    mark_pair(i, pair_count, verts_a, verts_b, vertex_body, moving_out)


@wp.kernel
def refresh_preconditioner(
    free: wp.array(dtype=wp.int32),
    diag_slot: wp.array(dtype=wp.int32),
    matrix: wp.array(dtype=wp.mat33),
    vertex_body: wp.array(dtype=wp.int32),
    solving: wp.array(dtype=wp.int32),
    diag_inv_out: wp.array(dtype=wp.mat33),
):
    """The inverse diagonal blocks again, zero on pinned vertices.

    With ``solving`` (per body, else empty), zero too on the bodies it does not mark: a solve with this
    preconditioner leaves them as they are.
    """
    i = wp.tid()
    if free[i] != 0:
        keep = solving.shape[0] == 0
        if not keep:
            keep = solving[vertex_body[i]] != 0
        diag_inv_out[i] = wp.where(keep, wp.inverse(matrix[diag_slot[i]]), wp.mat33())


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

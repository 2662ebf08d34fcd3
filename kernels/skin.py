"""The skin: dense vertices outside the coarse tets, embedded in a cell by extrapolating weights.

The static colliders act on them as on the tet vertices (``kernels.integrate``): at the step's start and in
its late passes. Most of a body's skin is far from any collider, so each of those launches is two: a light one
over every point lists the few a collider can reach within the step, and the contact's own kernel, whose
registers would hold back a launch over every point, runs over the list only.
"""

import warp as wp

from .embedding import interpolate
from .integrate import (
    FAR,
    MESH,
    Colliders,
    add_symmetric,
    collider_distance,
    collider_velocity,
    contact_from,
    late_contact,
    offset_depth,
    solid_distance,
)

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated

CLEAR_SLACK = 1.0e-6
"""How much more clearance (m) than its reach a skin point needs to be left out of a launch: the depth
tests' own float32 rounding (see :func:`skin_reach`, :func:`list_late_skin`)."""


@wp.func
def clearance(c: Colliders, o: int, distance: float, p: wp.vec3, body: int, dt: float) -> float:
    """How far (m) a point at signed ``distance`` from collider ``o`` may move in the step and not reach it.

    That is, the collider's offset, which itself moves at most ``dt |v_c|`` towards the point.
    """
    return -offset_depth(c, o, distance, body) - dt * wp.length(collider_velocity(c, o, p, dt))


@wp.kernel
def skin_reach(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    cells: wp.array(dtype=wp.vec4i),
    skin_cell: wp.array(dtype=wp.int32),
    skin_bary: wp.array(dtype=wp.vec4),
    cell_body: wp.array(dtype=wp.int32),
    body_momentum: wp.array(dtype=wp.vec3),
    body_mass: wp.array(dtype=float),
    colliders: Colliders,
    dt: float,
    listed_out: wp.array(dtype=wp.int32),
    list_out: wp.array(dtype=wp.int32),
    clear_out: wp.array(dtype=float),
):
    """List the skin points a static collider may act on this step, for :func:`skin_colliders`.

    A point acts with a collider only if it lies below the collider's offset or its own speed, or its body's,
    carries it there within the step (relative to the collider's speed: :func:`contact_from`), so a point whose
    clearance from every plane, sphere and box is more than ``dt`` times the larger of those speeds, plus what
    gravity adds in the step, is left out; its clearance goes to ``clear_out`` (where not empty) as
    :func:`skin_colliders` would give it. Every point is listed where a mesh collider is, whose distance
    needs the query this launch is too light to hold.
    """
    i = wp.tid()
    e = skin_cell[i]
    t = cells[e]
    w = skin_bary[i]
    xp = interpolate(x, t, w)
    body = cell_body[e]
    clear = float(FAR)
    near = bool(False)
    for o in range(colliders.kind.shape[0]):
        if colliders.kind[o] == MESH:
            near = True
        else:
            dn = solid_distance(colliders, o, wp.quat_rotate_inv(colliders.rotation[o], xp - colliders.center[o]))
            clear = wp.min(clear, clearance(colliders, o, dn[0], xp, body, dt))
    speed = wp.max(wp.length(interpolate(v, t, w)), wp.length(body_momentum[body] / body_mass[body]))
    if near or clear <= dt * (speed + dt * wp.length(colliders.gravity[0])) + CLEAR_SLACK:
        list_out[wp.atomic_add(listed_out, 0, 1)] = i
    elif clear_out.shape[0] > 0:
        clear_out[i] = clear / (wp.abs(w[0]) + wp.abs(w[1]) + wp.abs(w[2]) + wp.abs(w[3]))


@wp.kernel
def skin_colliders(
    listed: wp.array(dtype=wp.int32),
    skin_list: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    cells: wp.array(dtype=wp.vec4i),
    cell_slots: wp.array(dtype=wp.int32),
    skin_cell: wp.array(dtype=wp.int32),
    skin_bary: wp.array(dtype=wp.vec4),
    skin_mass: wp.array(dtype=float),
    cell_body: wp.array(dtype=wp.int32),
    body_momentum: wp.array(dtype=wp.vec3),
    body_mass: wp.array(dtype=float),
    colliders: Colliders,
    dt: float,
    force_out: wp.array(dtype=wp.vec3),
    matrix_out: wp.array(dtype=wp.mat33),
    clear_out: wp.array(dtype=float),
):
    """The static colliders acting on the skin points :func:`skin_reach` listed (dense vertices outside the tets).

    The same :func:`~warpfem.kernels.integrate.static_contact` as a vertex gets, at a point embedded in a cell
    (``x_p = sum w_k x_k``): its force goes to the cell's nodes by the weights ``w`` and its matrix term ``S``
    to their blocks as ``w_a w_b S`` (the weights of an outside point extrapolate, so some are negative; the
    term stays symmetric positive semi-definite).

    With ``clear_out``, each point's clearance: how far (m) its cell's nodes may move within the step without
    carrying it onto a collider. It lies ``-depth`` above each collider's offset, which moves at most
    ``dt |v_c|`` towards it, and moves at most ``sum |w_k|`` times as far as its fastest node; a late pass
    whose body's fastest node moves less than that cannot find it crossing (:func:`late_skin_contacts`).
    """
    k = wp.tid()
    if k >= listed[0]:
        return
    i = skin_list[k]
    e = skin_cell[i]
    t = cells[e]
    w = skin_bary[i]
    xp = interpolate(x, t, w)
    vp = interpolate(v, t, w)
    body = cell_body[e]
    v_body = body_momentum[body] / body_mass[body]
    clear = float(FAR)
    for o in range(colliders.kind.shape[0]):
        dn = collider_distance(colliders, o, xp)
        vc = collider_velocity(colliders, o, xp, dt)
        f, s = contact_from(colliders, o, dn, vc, vp, v_body, skin_mass[i], body, dt)
        if wp.trace(s) > 0.0:  # in contact (the matrix term is positive whenever the collider acts)
            for c in range(4):
                wp.atomic_add(force_out, t[c], w[c] * f)
            add_symmetric(matrix_out, cell_slots, e, w, s)
        clear = wp.min(clear, clearance(colliders, o, dn[0], xp, body, dt))
    if clear_out.shape[0] > 0:
        clear_out[i] = clear / (wp.abs(w[0]) + wp.abs(w[1]) + wp.abs(w[2]) + wp.abs(w[3]))


@wp.kernel
def list_late_skin(
    late: wp.array(dtype=wp.int32),
    skin_cell: wp.array(dtype=wp.int32),
    cell_body: wp.array(dtype=wp.int32),
    dt: float,
    clear: wp.array(dtype=float),
    body_speed: wp.array(dtype=float),
    listed_out: wp.array(dtype=wp.int32),
    list_out: wp.array(dtype=wp.int32),
):
    """The skin points a late pass reads (:func:`late_skin_contacts`), appended to ``list_out``.

    Those not yet given a contact this step (``late``) whose clearance at the step's start (``clear``, from
    :func:`skin_reach` or :func:`skin_colliders`) their body's fastest node (``body_speed``, m/s) can cover
    within the step; every one not given a contact where ``clear`` is empty. A light launch over every point,
    so that the contact's own registers are spent on the few it lists.
    """
    i = wp.tid()
    if late[i] != 0:
        return
    if clear.shape[0] > 0 and clear[i] > dt * body_speed[cell_body[skin_cell[i]]] + CLEAR_SLACK:
        return
    list_out[wp.atomic_add(listed_out, 0, 1)] = i


@wp.kernel
def late_skin_contacts(
    listed: wp.array(dtype=wp.int32),
    skin_list: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    v_new: wp.array(dtype=wp.vec3),
    cells: wp.array(dtype=wp.vec4i),
    cell_slots: wp.array(dtype=wp.int32),
    free: wp.array(dtype=wp.int32),
    skin_cell: wp.array(dtype=wp.int32),
    skin_bary: wp.array(dtype=wp.vec4),
    skin_mass: wp.array(dtype=float),
    cell_body: wp.array(dtype=wp.int32),
    body_momentum: wp.array(dtype=wp.vec3),
    body_mass: wp.array(dtype=float),
    colliders: Colliders,
    dt: float,
    late_out: wp.array(dtype=wp.int32),
    count_out: wp.array(dtype=wp.int32),
    matrix_out: wp.array(dtype=wp.mat33),
    rhs_out: wp.array(dtype=wp.vec3),
    matrix_base_out: wp.array(dtype=wp.mat33),
    rhs_base_out: wp.array(dtype=wp.vec3),
):
    """:func:`late_contact` on each skin point :func:`list_late_skin` listed (the first ``listed[0]`` of ``skin_list``).

    Its force goes to the right-hand side of its cell's free nodes by the weights, ``w_a w_b S`` to the
    cell's blocks (and to the system without elasticity, as :func:`late_vertex_contacts`); it is marked and
    counted as there.
    """
    k = wp.tid()
    if k >= listed[0]:
        return
    i = skin_list[k]
    e = skin_cell[i]
    body = cell_body[e]
    t = cells[e]
    w = skin_bary[i]
    v_body = body_momentum[body] / body_mass[body]
    for o in range(colliders.kind.shape[0]):
        f, s = late_contact(
            colliders,
            o,
            interpolate(x, t, w),
            interpolate(v, t, w),
            interpolate(v_new, t, w),
            v_body,
            skin_mass[i],
            body,
            dt,
        )
        if wp.trace(s) > 0.0:
            for c in range(4):
                if free[t[c]] != 0:
                    wp.atomic_add(rhs_out, t[c], dt * w[c] * f)
                    if rhs_base_out.shape[0] > 0:
                        wp.atomic_add(rhs_base_out, t[c], dt * w[c] * f)
            add_symmetric(matrix_out, cell_slots, e, w, s)
            if rhs_base_out.shape[0] > 0:
                add_symmetric(matrix_base_out, cell_slots, e, w, s)
            late_out[i] = 1
            wp.atomic_add(count_out, 0, 1)

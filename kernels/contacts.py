"""The penalty response of the contacts detection found: forces, the implicit terms CG applies, friction.

Each contact pushes its point out along its direction with ``f = a d g`` and its image in the other body's cell
back by ``-f``, so momentum is conserved; its 3x3 term couples the two embedded points in CG's product
(:class:`warpfem.sim.contacts.Coupling`). Also the marks of points a run starts with placed inside another body.
"""

import warp as wp

from .integrate import tie_friction

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated


@wp.func
def relative(field: wp.array(dtype=wp.vec3), tp: wp.vec4i, w_p: wp.vec4, tt: wp.vec4i, w_t: wp.vec4) -> wp.vec3:
    """A per-vertex field at a contact's point minus at its image in the tet: J applied to ``field``."""
    r = wp.vec3()
    for k in range(4):
        r += w_p[k] * field[tp[k]] - w_t[k] * field[tt[k]]
    return r


@wp.func
def mark_contact(point_contact_out: wp.array(dtype=wp.int32), p: int, body: int):
    """Mark point p as in contact with ``body``: ``body + 1`` for its first contact's body, -1 once it has two.

    Whatever order contacts of several bodies mark a point in, it ends at -1: each that replaces another body's
    mark writes -1 after it.
    """
    old = wp.atomic_exch(point_contact_out, p, body + 1)
    if old != 0 and old != body + 1:
        point_contact_out[p] = -1


@wp.kernel
def contact_forces(
    # inputs: contacts
    count: wp.array(dtype=wp.int32),
    contact_point: wp.array(dtype=wp.int32),
    contact_cell: wp.array(dtype=wp.int32),
    contact_bary: wp.array(dtype=wp.vec4),
    contact_normal: wp.array(dtype=wp.vec3),
    contact_depth: wp.array(dtype=float),
    # inputs: model and state
    v: wp.array(dtype=wp.vec3),
    cells: wp.array(dtype=wp.vec4i),
    cell_body: wp.array(dtype=wp.int32),
    point_cell: wp.array(dtype=wp.int32),
    point_bary: wp.array(dtype=wp.vec4),
    point_stiffness: wp.array(dtype=float),
    point_mass: wp.array(dtype=float),
    damping: float,
    closing_depth: float,
    friction: wp.array(dtype=float),
    diag_slot: wp.array(dtype=wp.int32),
    dt: float,
    first: wp.array(dtype=wp.int32),
    late: int,
    solve_depth: float,
    # outputs
    pair_verts_a_out: wp.array(dtype=wp.vec4i),
    pair_weights_a_out: wp.array(dtype=wp.vec4),
    pair_verts_b_out: wp.array(dtype=wp.vec4i),
    pair_weights_b_out: wp.array(dtype=wp.vec4),
    contact_matrix_out: wp.array(dtype=wp.mat33),
    force_out: wp.array(dtype=wp.vec3),
    matrix_out: wp.array(dtype=wp.mat33),
    totals_out: wp.array(dtype=wp.int32),
    point_contact_out: wp.array(dtype=wp.int32),
    late_count_out: wp.array(dtype=wp.int32),
    placed_out: wp.array(dtype=wp.int32),
):
    """Penalty force a d g on the point's cell nodes (by its weights), the reaction on the contact cell's.

    The contacts from ``first[0]`` on. ``late``: contacts a late pass found (see
    :func:`kernels.collision.store_contact`), after the system was built: ``force_out`` is then the right-hand
    side (the force enters times dt), the totals are left alone and ``late_count_out[0]`` counts the contacts
    that end the step deeper than ``solve_depth`` (m), which ask for a second solve; shallower ones stay outside
    the visible surface, or within a share of the offset of it, and the next step answers them from its start.
    Each contact's point is marked in ``point_contact_out`` (:func:`mark_contact`), so a late pass does not
    answer it twice.

    Each contact couples the relative velocity u = v_point - v_image (point minus its image in the tet)
    through C = dt^2 a g g^T + dt c (I - g g^T): the linearised penalty along g and implicit Coulomb-like
    friction across it; a contact closing by more than ``closing_depth`` (m) in the step adds a damper along g,
    ``dt b g g^T`` with ``b = 2 damping sqrt(a m_p)`` (``damping`` times critical for the point's mass
    ``point_mass`` on its spring). c from :func:`kernels.integrate.tie_friction` at the step's start velocity
    and a depth of at most ``friction[1]`` (m; ``friction[0]``: the coefficient), none for a point ``placed_out`` marks
    while its contact is deeper than that (it clears the mark once one is not: :func:`mark_placed`). C goes to
    ``contact_matrix_out`` and the two embedded points to ``pair_*_out`` for the matrix-free product in CG
    (:class:`warpfem.sim.contacts.Coupling`); its diagonal blocks to the matrix. Thread 0 also adds the step's
    contacts found to ``totals_out[0]`` and keeps the most in one step in ``totals_out[1]``.
    """
    i = wp.tid() + first[0]
    last = wp.min(count[0], contact_point.shape[0])
    if i == first[0] and late == 0:
        totals_out[0] = totals_out[0] + count[0]
        totals_out[1] = wp.max(totals_out[1], count[0])
    if i >= last:
        return
    p = contact_point[i]
    mark_contact(point_contact_out, p, cell_body[contact_cell[i]])
    a = point_stiffness[p]
    g = contact_normal[i]
    f = a * contact_depth[i] * g
    if late != 0:
        f = dt * f
    tp = cells[point_cell[p]]
    w_p = point_bary[p]
    tt = cells[contact_cell[i]]
    w_t = contact_bary[i]
    u = relative(v, tp, w_p, tt, w_t)
    if late != 0 and contact_depth[i] - dt * wp.dot(g, u) > solve_depth:
        wp.atomic_add(late_count_out, 0, 1)  # its depth at the end of the step, with the answer's velocities
    ut = u - wp.dot(u, g) * g
    loaded = wp.min(contact_depth[i], friction[1])
    if placed_out[p] != 0:
        if contact_depth[i] > friction[1]:
            loaded = 0.0
        else:
            placed_out[p] = 0
    c = tie_friction(friction[0], a, loaded, wp.length(ut), dt)
    gg = wp.outer(g, g)
    C = dt * dt * a * gg + dt * c * (wp.identity(n=3, dtype=float) - gg)
    if damping > 0.0 and -wp.dot(u, g) * dt > closing_depth:
        # closing fast: a damper along the way out, ``damping`` times critical for the point's mass on its spring
        C += dt * 2.0 * damping * wp.sqrt(a * point_mass[p]) * gg
    contact_matrix_out[i] = C
    pair_verts_a_out[i] = tp
    pair_weights_a_out[i] = w_p
    pair_verts_b_out[i] = tt
    pair_weights_b_out[i] = w_t
    for k in range(4):
        wp.atomic_add(force_out, tp[k], w_p[k] * f)
        wp.atomic_add(force_out, tt[k], -w_t[k] * f)
        wp.atomic_add(matrix_out, diag_slot[tp[k]], w_p[k] * w_p[k] * C)
        wp.atomic_add(matrix_out, diag_slot[tt[k]], w_t[k] * w_t[k] * C)


@wp.kernel
def mark_placed(
    count: wp.array(dtype=wp.int32),
    contact_point: wp.array(dtype=wp.int32),
    contact_depth: wp.array(dtype=float),
    friction: wp.array(dtype=float),
    placed_out: wp.array(dtype=wp.int32),
):
    """Marks the point of each contact deeper than friction's load depth ``friction[1]`` (m) as placed inside.

    Run on the contacts of the state a run starts from: such a point lies in an overlap the bodies were put in,
    whose penalties squeeze a body from opposite sides; friction from them would hold it there.
    """
    i = wp.tid()
    if i < wp.min(count[0], contact_point.shape[0]) and contact_depth[i] > friction[1]:
        placed_out[contact_point[i]] = 1


@wp.kernel
def release_placed(point_contact: wp.array(dtype=wp.int32), placed_out: wp.array(dtype=wp.int32)):
    """Clears the placed-inside mark of each point the last step found no contact for: it is out of the overlap."""
    p = wp.tid()
    if point_contact[p] == 0:
        placed_out[p] = 0


@wp.kernel
def scale_point_stiffness(
    point_mass: wp.array(dtype=float), stiffness: float, point_stiffness_out: wp.array(dtype=float)
):
    """a_p = stiffness * m_p (N/m)."""
    i = wp.tid()
    point_stiffness_out[i] = stiffness * point_mass[i]

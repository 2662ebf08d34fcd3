"""Fast approach between bodies: whether a frame's steps would carry two bodies too far into each other.

From the state at a frame's start, two ways to close fast: bodies not yet touching whose mean velocities
(momentum over mass) close on each other and whose boxes lie within a frame's travel (:func:`approach`), and
the contacts of the last step whose points close on their images (:func:`contacts_closing`). Either, by more
than a level's limit times the smaller body's size in one step, raises that level's flag.
"""

import warp as wp

from .embedding import interpolate
from .grid import warp_sum_at

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated


@wp.kernel
def clear_bodies(
    momentum_out: wp.array(dtype=wp.vec3),
    lower_out: wp.array(dtype=wp.vec3),
    upper_out: wp.array(dtype=wp.vec3),
    flags_out: wp.array(dtype=wp.int32),
):
    """Per body: zero momentum, an empty box; thread 0 lowers the frame's flags."""
    b = wp.tid()
    momentum_out[b] = wp.vec3(0.0)
    lower_out[b] = wp.vec3(1.0e30)
    upper_out[b] = wp.vec3(-1.0e30)
    if b == 0:
        for k in range(flags_out.shape[0]):
            flags_out[k] = 0


@wp.func
def raise_flags(closing: float, limits: wp.array(dtype=float), flags_out: wp.array(dtype=wp.int32)):
    """Raise flag k where ``closing`` (a share of the smaller size, per step) exceeds ``limits[k]``."""
    for k in range(limits.shape[0]):
        if closing > limits[k]:
            flags_out[k] = 1


@wp.kernel
def body_extent(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    vertex_body: wp.array(dtype=wp.int32),
    momentum_out: wp.array(dtype=wp.vec3),
    lower_out: wp.array(dtype=wp.vec3),
    upper_out: wp.array(dtype=wp.vec3),
):
    """Per vertex: its momentum (kg m/s) added to its body's, its position to its body's box.

    The momentum one atomic per warp of one body, as ``kernels.integrate.body_momentum`` sums it.
    """
    i = wp.tid()
    b = vertex_body[i]
    warp_sum_at(mass[i] * v[i], b, momentum_out)
    wp.atomic_min(lower_out, b, x[i])
    wp.atomic_max(upper_out, b, x[i])


@wp.func
def mean_velocity(momentum: wp.array(dtype=wp.vec3), body_mass: wp.array(dtype=float), b: int) -> wp.vec3:
    """Body b's mean velocity (m/s); zero for a body without mass."""
    if body_mass[b] <= 0.0:
        return wp.vec3(0.0)
    return momentum[b] / body_mass[b]


@wp.kernel
def approach(
    momentum: wp.array(dtype=wp.vec3),
    body_mass: wp.array(dtype=float),
    lower: wp.array(dtype=wp.vec3),
    upper: wp.array(dtype=wp.vec3),
    size: wp.array(dtype=float),
    frame_dt: float,
    step_dt: float,
    limits: wp.array(dtype=float),
    flags_out: wp.array(dtype=wp.int32),
):
    """Per body i, against every later body j: raise the flags where the two are near and close fast.

    Near: i's and j's boxes lie within the distance their mean velocities carry them in ``frame_dt`` (s).
    Fast: their mean velocities differ by more than ``limits[k]`` times the smaller size (m) per ``step_dt``
    (s), for flag k.
    """
    i = wp.tid()
    v_i = mean_velocity(momentum, body_mass, i)
    for j in range(i + 1, size.shape[0]):
        v_j = mean_velocity(momentum, body_mass, j)
        reach = (wp.length(v_i) + wp.length(v_j)) * frame_dt
        gap = wp.max(lower[j] - upper[i], lower[i] - upper[j])  # per axis, how far apart the boxes are
        if wp.max(gap[0], wp.max(gap[1], gap[2])) <= reach:
            raise_flags(wp.length(v_i - v_j) * step_dt / wp.min(size[i], size[j]), limits, flags_out)


@wp.kernel
def contacts_closing(
    count: wp.array(dtype=wp.int32),
    contact_point: wp.array(dtype=wp.int32),
    contact_cell: wp.array(dtype=wp.int32),
    contact_bary: wp.array(dtype=wp.vec4),
    contact_normal: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    cells: wp.array(dtype=wp.vec4i),
    point_cell: wp.array(dtype=wp.int32),
    point_bary: wp.array(dtype=wp.vec4),
    vertex_body: wp.array(dtype=wp.int32),
    size: wp.array(dtype=float),
    step_dt: float,
    limits: wp.array(dtype=float),
    flags_out: wp.array(dtype=wp.int32),
):
    """Per contact of the last step: raise the flags where its point closes on its image fast.

    Faster: by more than ``limits[k]`` times the smaller body's size (m) per ``step_dt`` (s), at velocities
    ``v``, for flag k.
    """
    i = wp.tid()
    if i >= wp.min(count[0], contact_point.shape[0]):
        return
    p = contact_point[i]
    tp = cells[point_cell[p]]
    tt = cells[contact_cell[i]]
    u = interpolate(v, tp, point_bary[p]) - interpolate(v, tt, contact_bary[i])
    smaller = wp.min(size[vertex_body[tp[0]]], size[vertex_body[tt[0]]])
    raise_flags(-wp.dot(u, contact_normal[i]) * step_dt / smaller, limits, flags_out)


@wp.kernel
def count_frame(count_out: wp.array(dtype=wp.int32)):
    """One more frame run at a refined level."""
    count_out[0] = count_out[0] + 1

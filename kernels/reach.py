"""Which bodies lie out of the still colliders' reach: a bound per body, so that their points skip the per-point tests.

A point embedded in a cell (``x_p = sum w_k x_k``, the weights summing to one) lies within its cell's box grown
by ``(spread - 1) / 2`` of the box's extent per axis, where ``spread = sum |w_k|``; so every such point of a body
lies within the body's box of tet nodes grown by its largest ``(spread - 1) / 2`` times that box's extent, and
moves at most ``spread`` times as fast as the body's fastest node. A plane's, a sphere's and a box's signed
distances change by at most the distance moved, so the distance at the grown box's centre less its half
diagonal bounds every point's from below (a mesh's does not: it reads as far outside past its reach).
"""

import warp as wp

from .integrate import BOX, CLEAR_SLACK, FAR, LIFT_GIVE, PLANE, SPHERE, Colliders, collider_distance

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated


@wp.kernel
def clear_bounds(
    lower_out: wp.array(dtype=wp.vec3), upper_out: wp.array(dtype=wp.vec3), speed_out: wp.array(dtype=float)
):
    """Per body: an empty box and no speed."""
    b = wp.tid()
    lower_out[b] = wp.vec3(FAR)
    upper_out[b] = wp.vec3(-FAR)
    if speed_out.shape[0] > 0:
        speed_out[b] = 0.0


@wp.kernel
def body_bounds(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    vertex_body: wp.array(dtype=wp.int32),
    lower_out: wp.array(dtype=wp.vec3),
    upper_out: wp.array(dtype=wp.vec3),
    speed_out: wp.array(dtype=float),
):
    """Per tet node: its position into its body's box, its speed (m/s) into the body's fastest (where asked)."""
    i = wp.tid()
    b = vertex_body[i]
    wp.atomic_min(lower_out, b, x[i])
    wp.atomic_max(upper_out, b, x[i])
    if speed_out.shape[0] > 0:
        wp.atomic_max(speed_out, b, wp.length(v[i]))


@wp.func
def distance_below(c: Colliders, lower: wp.vec3, upper: wp.vec3, spread: float, offset: bool, body: int) -> float:
    """The least signed distance (m) any point of the body can have from a still collider.

    The body: box ``lower``-``upper`` of its nodes, ``spread`` the largest ``sum |w|`` of its points. Less the
    collider's offset for that body where ``offset``; -FAR where a collider moves or is a mesh (no bound), FAR
    where there is none.
    """
    grow = 0.5 * (spread - 1.0) * (upper - lower)
    centre = 0.5 * (lower + upper)
    half = wp.length(0.5 * (upper - lower) + grow)
    least = float(FAR)
    for o in range(c.kind.shape[0]):
        kind = c.kind[o]
        if c.moving[o] != 0 or not (kind == PLANE or kind == SPHERE or kind == BOX):
            return -FAR
        d = collider_distance(c, o, centre)[0] - half
        if offset:
            d -= c.response[o][2] * c.body_size[body]
        least = wp.min(least, d)
    return least


@wp.kernel
def static_clearance(
    lower: wp.array(dtype=wp.vec3),
    upper: wp.array(dtype=wp.vec3),
    speed: wp.array(dtype=float),
    spread: wp.array(dtype=float),
    colliders: Colliders,
    dt: float,
    clear_out: wp.array(dtype=float),
):
    """Per body at the step's start: a lower bound of its skin points' clearance where none can touch a collider.

    Else -1; ``kernels.integrate.skin_colliders`` skips the points of a body given one. None can where the bound
    exceeds how far its fastest point moves in the step: ``spread`` times its fastest node's speed times ``dt``
    (s). The clearance a point reports is its own divided by its ``sum |w|``, so the body's divided by
    ``spread`` bounds it.
    """
    b = wp.tid()
    s = spread[b]
    clear = distance_below(colliders, lower[b], upper[b], s, True, b)
    if clear > dt * s * speed[b] + CLEAR_SLACK:
        clear_out[b] = clear / s
    else:
        clear_out[b] = -1.0


@wp.kernel
def lift_clearance(
    lower: wp.array(dtype=wp.vec3),
    upper: wp.array(dtype=wp.vec3),
    spread: wp.array(dtype=float),
    colliders: Colliders,
    free_out: wp.array(dtype=wp.int32),
):
    """Per body: 1 where no point of it can lie below a still collider by more than the lift's give, else 0.

    ``kernels.integrate.lift_points`` skips the points of a body marked 1.
    """
    b = wp.tid()
    least = distance_below(colliders, lower[b], upper[b], spread[b], False, b)
    free_out[b] = wp.where(least >= -LIFT_GIVE * colliders.body_size[b], 1, 0)

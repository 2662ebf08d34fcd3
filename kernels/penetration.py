"""The independent penetration check's device code: how deep dense vertices sit inside other bodies' surfaces.

One thread per dense vertex: the bodies whose bounding box holds it (a BVH over the boxes), the winding
number of each one's dense surface (``wp.Mesh``) around it, and only where it is inside, its distance to that
surface (the closest-point search is the costly part), kept per body as the deepest with its vertex's owner
packed into one int64 (an atomic max). Mesh obstacles likewise: one thread per dense vertex, its depth inside
a closed obstacle mesh or behind an open one, folded into the body's deepest (an atomic max).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated

DEPTH_BITS = wp.constant(40)
"""Bits of the packed depth: its fraction of the body's reach, so a resolution of 2^-40 of the body's size."""

OWNER_BITS = wp.constant(20)
"""Bits of the packed owner (the body whose vertex it is): up to 2^20 bodies."""


@wp.func_native("return wp::mesh_query_winding_number(id, p, accuracy);")
def winding_number(id: wp.uint64, p: wp.vec3, accuracy: float) -> float:
    """The generalized winding number of mesh ``id`` around ``p`` (Warp's dipole approximation, as its sign queries).

    Warp exposes it only inside ``mesh_query_point_sign_winding_number``, after a closest-point search that
    costs four times the winding number on the many points of a box that are outside the body.
    """
    ...


@wp.kernel
def deepest_inside(
    points: wp.array(dtype=wp.vec3),
    owner: wp.array(dtype=wp.int32),
    boxes: wp.uint64,
    box_body: wp.array(dtype=wp.int32),
    meshes: wp.array(dtype=wp.uint64),
    reach: wp.array(dtype=float),
    accuracy: float,
    deepest: wp.array(dtype=wp.int64),
):
    """Fold each vertex's depth inside every other body whose box holds it into ``deepest[body]``.

    ``deepest[j]`` packs ``(depth / reach[j] * 2^DEPTH_BITS) << OWNER_BITS | owner``: the larger the deeper.
    ``reach[j]`` (m) bounds the distance from a point in j's box to j's surface (its box diagonal, padded).
    """
    t = wp.tid()
    p = points[t]
    i = owner[t]
    query = wp.bvh_query_aabb(boxes, p, p)
    item = int(0)
    while wp.bvh_query_next(query, item):
        j = box_body[item]
        if j != i:
            if winding_number(meshes[j], p, accuracy) > 0.5:
                q = wp.mesh_query_point_no_sign(meshes[j], p, reach[j])
                if q.result:
                    depth = wp.length(p - wp.mesh_eval_position(meshes[j], q.face, q.u, q.v))
                    fraction = wp.min(depth / reach[j], 1.0)
                    quantised = wp.int64(fraction * wp.pow(2.0, float(DEPTH_BITS)))
                    wp.atomic_max(deepest, j, (quantised << wp.int64(OWNER_BITS)) | wp.int64(i))


@wp.kernel
def body_bounds(
    points: wp.array(dtype=wp.vec3),
    chunk_start: wp.array(dtype=wp.int32),
    chunk_body: wp.array(dtype=wp.int32),
    bounds: wp.array(dtype=wp.vec3),
):
    """Fold chunk i (points ``chunk_start[i]`` to ``chunk_start[i + 1]``, all of one body) into that body's box.

    ``bounds[2 b]`` and ``bounds[2 b + 1]`` are body b's lower and upper corners, reset to +inf and -inf
    before the launch. A non-finite point makes its body's box infinite both ways, so a reader of the box
    alone sees that the points are not finite.
    """
    i = wp.tid()
    b = chunk_body[i]
    lo = wp.vec3(wp.inf, wp.inf, wp.inf)
    hi = wp.vec3(-wp.inf, -wp.inf, -wp.inf)
    for k in range(chunk_start[i], chunk_start[i + 1]):
        p = points[k]
        if wp.isfinite(p):
            lo = wp.min(lo, p)
            hi = wp.max(hi, p)
        else:
            lo = wp.vec3(-wp.inf, -wp.inf, -wp.inf)
            hi = wp.vec3(wp.inf, wp.inf, wp.inf)
    wp.atomic_min(bounds, 2 * b, lo)
    wp.atomic_max(bounds, 2 * b + 1, hi)


@wp.kernel
def check_boxes(
    bounds: wp.array(dtype=wp.vec3),
    body_box: wp.array(dtype=wp.int32),
    pad: float,
    lowers: wp.array(dtype=wp.vec3),
    uppers: wp.array(dtype=wp.vec3),
    reach: wp.array(dtype=float),
):
    """Body b's box in the check's tree (``body_box[b]``, -1: none) and its reach, from its bounds.

    The box is padded by ``pad`` times the body's size (its diagonal); the reach is the padded diagonal.
    """
    b = wp.tid()
    lo = bounds[2 * b]
    hi = bounds[2 * b + 1]
    margin = pad * wp.max(wp.length(hi - lo), 1.0e-30)
    reach[b] = wp.length(hi - lo) + 2.0 * margin
    k = body_box[b]
    if k >= 0:
        lowers[k] = lo - wp.vec3(margin, margin, margin)
        uppers[k] = hi + wp.vec3(margin, margin, margin)


OPEN_EDGE_WEIGHT = wp.constant(1.0e-5)
"""A barycentric weight below which the nearest point counts as on the edge opposite that corner."""


@wp.struct
class MeshObstacle:
    """A mesh obstacle's surface in its own frame and where it is: what :func:`obstacle_depth` reads.

    ``inverse`` and ``translation`` take a world point into the obstacle's frame (``inverse (p - translation)``);
    ``lower`` and ``upper`` bound the points it can hold there (its box, padded by ``reach`` when open); ``reach``
    (m) is how far a point may be from its surface (an open mesh's thickness; for a closed one, twice its box
    diagonal: beyond any point of its box).
    ``flags`` per face: bits 0-2 its edges a-b, b-c, c-a that no other face shares, bits 3-5 its corners a, b, c
    on such an edge.
    """

    mesh: wp.uint64
    inverse: wp.mat33
    translation: wp.vec3
    lower: wp.vec3
    upper: wp.vec3
    closed: int
    reach: float
    flags: wp.array(dtype=wp.int32)


@wp.func
def on_open_edge(flags: int, wa: float, wb: float, wc: float) -> bool:
    """Whether a point of weights (wa, wb, wc) on a face with ``flags`` lies on an open edge or an open corner."""
    na = wa < OPEN_EDGE_WEIGHT
    nb = wb < OPEN_EDGE_WEIGHT
    nc = wc < OPEN_EDGE_WEIGHT
    edge = ((flags & 1) != 0 and nc) or ((flags & 2) != 0 and na) or ((flags & 4) != 0 and nb)
    corner = ((flags & 8) != 0 and nb and nc) or ((flags & 16) != 0 and nc and na) or ((flags & 32) != 0 and na and nb)
    return edge or corner


@wp.func
def in_box(q: wp.vec3, lower: wp.vec3, upper: wp.vec3) -> bool:
    """Whether ``q`` lies in the box from ``lower`` to ``upper`` (bounds included; never for a non-finite point)."""
    inside = True
    for k in range(3):
        inside = inside and q[k] >= lower[k] and q[k] <= upper[k]
    return inside


@wp.func
def obstacle_depth(o: MeshObstacle, p: wp.vec3, accuracy: float) -> float:
    """How deep world point ``p`` is in mesh obstacle ``o`` (m; 0 outside).

    Closed: where its surface winds around the point (winding number > 0.5), the distance to the surface.
    Open: the distance to the nearest surface point where that point is not on an open edge or corner, the
    point is on that face's back side and at most ``reach`` from it.
    """
    q = o.inverse @ (p - o.translation)
    if not in_box(q, o.lower, o.upper):
        return 0.0
    if o.closed != 0 and winding_number(o.mesh, q, accuracy) <= 0.5:
        return 0.0
    hit = wp.mesh_query_point_no_sign(o.mesh, q, o.reach * 1.000001)
    if not hit.result:
        return 0.0
    a = wp.mesh_get_point(o.mesh, hit.face * 3)
    b = wp.mesh_get_point(o.mesh, hit.face * 3 + 1)
    c = wp.mesh_get_point(o.mesh, hit.face * 3 + 2)
    w = 1.0 - hit.u - hit.v
    offset = q - (a * hit.u + b * hit.v + c * w)
    depth = wp.length(offset)
    if o.closed != 0:
        return depth
    if depth > o.reach or wp.dot(offset, wp.cross(b - a, c - a)) >= 0.0:
        return 0.0
    if on_open_edge(o.flags[hit.face], hit.u, hit.v, w):
        return 0.0
    return depth


@wp.kernel
def obstacle_depths(
    points: wp.array(dtype=wp.vec3), obstacle: MeshObstacle, accuracy: float, depths: wp.array(dtype=float)
):
    """Each point's depth in a mesh obstacle (m; :func:`obstacle_depth`)."""
    t = wp.tid()
    depths[t] = obstacle_depth(obstacle, points[t], accuracy)


@wp.kernel
def deepest_in_obstacle(
    points: wp.array(dtype=wp.vec3),
    obstacle: MeshObstacle,
    accuracy: float,
    slot: int,
    deepest: wp.array(dtype=float),
):
    """Fold the points' depths in a mesh obstacle into ``deepest[slot]`` (m; an atomic max, reset to 0)."""
    t = wp.tid()
    depth = obstacle_depth(obstacle, points[t], accuracy)
    if depth > 0.0:
        wp.atomic_max(deepest, slot, depth)

"""The independent penetration check's device code: how deep dense vertices sit inside other bodies' surfaces.

One thread per dense vertex: the bodies whose bounding box holds it (a BVH over the boxes), the winding
number of each one's dense surface (``wp.Mesh``) around it, and only where it is inside, its distance to that
surface (the closest-point search is the costly part), kept per body as the deepest with its vertex's owner
packed into one int64 (an atomic max).
"""

import warp as wp

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

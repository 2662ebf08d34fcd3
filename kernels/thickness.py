"""Local thickness of a closed surface: the distance along the inward normal to the surface's other side."""

import warp as wp

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated


@wp.kernel
def inward_ray(
    starts: wp.array(dtype=wp.vec3),
    inward: wp.array(dtype=wp.vec3),
    surface: wp.uint64,
    offset: float,
    max_t: float,
    thickness_out: wp.array(dtype=float),
):
    """Distance from each start point along its inward direction to the first surface hit, or -1 for none.

    The ray starts ``offset`` inside the surface so that it does not hit the faces around its own start.
    """
    i = wp.tid()
    d = inward[i]
    hit = wp.mesh_query_ray(surface, starts[i] + offset * d, d, max_t)
    if hit.result:
        thickness_out[i] = hit.t + offset
    else:
        thickness_out[i] = -1.0

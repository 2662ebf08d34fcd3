"""Distance field at tet vertices (Fisher & Lin 2001): signed depth below the surface and its outward gradient."""

import warp as wp


@wp.kernel
def surface_distance(
    points: wp.array(dtype=wp.vec3),
    surface: wp.uint64,
    surface_indices: wp.array(dtype=wp.int32),
    surface_normals: wp.array(dtype=wp.vec3),
    max_dist: float,
    on_surface: float,
    depth_out: wp.array(dtype=float),
    grad_out: wp.array(dtype=wp.vec3),
):
    """Signed depth of each point below the surface mesh (negative outside) and the unit direction out of it.

    The side comes from the generalized winding number. Away from the surface the direction is along the
    line to the closest surface point, pointing out of the body; within ``on_surface`` of it (depth set to 0)
    it is the vertex normals interpolated at the closest point. Depth -1e30 where no face is in reach.
    """
    i = wp.tid()
    p = points[i]
    hit = wp.mesh_query_point_sign_winding_number(surface, p, max_dist)
    if not hit.result:
        depth_out[i] = -1.0e30
        grad_out[i] = wp.vec3(0.0)
        return
    closest = wp.mesh_eval_position(surface, hit.face, hit.u, hit.v)
    offset = closest - p
    dist = wp.length(offset)
    if dist > on_surface:
        if hit.sign < 0.0:
            depth_out[i] = dist
            grad_out[i] = offset / dist
        else:
            depth_out[i] = -dist
            grad_out[i] = -offset / dist
    else:
        w = 1.0 - hit.u - hit.v
        n = (
            hit.u * surface_normals[surface_indices[3 * hit.face]]
            + hit.v * surface_normals[surface_indices[3 * hit.face + 1]]
            + w * surface_normals[surface_indices[3 * hit.face + 2]]
        )
        depth_out[i] = 0.0
        grad_out[i] = wp.normalize(n)


@wp.kernel
def unsigned_distance(
    points: wp.array(dtype=wp.vec3),
    surface: wp.uint64,
    max_dist: float,
    distance_out: wp.array(dtype=float),
):
    """Distance from each point to the closest point of the surface mesh (-1 if none within max_dist)."""
    i = wp.tid()
    p = points[i]
    hit = wp.mesh_query_point_no_sign(surface, p, max_dist)
    if hit.result:
        distance_out[i] = wp.length(wp.mesh_eval_position(surface, hit.face, hit.u, hit.v) - p)
    else:
        distance_out[i] = -1.0


@wp.func
def add_rotated_gradients(
    t: wp.vec4i, R: wp.mat33, rest_grad: wp.array(dtype=wp.vec3), grad_out: wp.array(dtype=wp.vec3)
):
    """grad[v] += R g0[v] for the four corners v of a tet turned by R (Kondo & Kanai step 7, unnormalised)."""
    for a in range(4):
        wp.atomic_add(grad_out, t[a], R * rest_grad[t[a]])


@wp.func
def direction_at(grad: wp.array(dtype=wp.vec3), v: int) -> wp.vec3:
    """normalize(sum_k R_k g0) at tet vertex v from the accumulated sum (zero stays zero)."""
    g = grad[v]
    n = wp.length(g)
    if n > 0.0:
        return g / n
    return g


@wp.func
def interpolate_directions(grad: wp.array(dtype=wp.vec3), tet: wp.vec4i, w: wp.vec4) -> wp.vec3:
    """The rotated gradients of a tet's corners, each normalised, blended with barycentric weights w."""
    return (
        w[0] * direction_at(grad, tet[0])
        + w[1] * direction_at(grad, tet[1])
        + w[2] * direction_at(grad, tet[2])
        + w[3] * direction_at(grad, tet[3])
    )

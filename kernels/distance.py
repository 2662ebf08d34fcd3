"""Distances to a surface mesh, for preprocessing.

The distance field at tet vertices (Fisher & Lin 2001), and the layout of the surface faces' lattice of
depths that preprocessing fills.

The simulation's depths below the visible surface are in :mod:`warpfem.kernels.surface`.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated


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


LATTICE = 8
"""Each surface face carries the depth of the visible surface below it at the points of a lattice that
splits it into LATTICE^2 triangles: a cage face lies farther from a dense bulge at its corners than at its
middle, which the corners' depths alone miss (preprocessing fills it: ``warpfem.prep.geometry.face_lattice``).
The finer the lattice, the more points near a surface it proves outside without asking the dense surface
(``warpfem.kernels.collision.depth_above``)."""

LATTICE_POINTS = (LATTICE + 1) * (LATTICE + 2) // 2

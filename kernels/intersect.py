"""Triangle-triangle intersection tests over a ``wp.Mesh`` BVH (self-intersection detection).

Two non-coplanar triangles intersect exactly when an edge of one crosses the other: the ends of their
intersection segment lie on edges. Triangles sharing one corner meet there anyway; they intersect
elsewhere exactly when the edge opposite the shared corner of one of them crosses the other. Triangles
sharing an edge are neighbours and are not tested; nor are coplanar pairs. Positions are float64.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated

COPLANAR = wp.constant(wp.float64(1.0e-12))
"""Relative orientation (to the product of the lengths involved) below which a point is in a plane."""


@wp.func
def orient(a: wp.vec3d, b: wp.vec3d, c: wp.vec3d, d: wp.vec3d) -> wp.float64:
    """Six times the signed volume of the tet (a, b, c, d)."""
    return wp.dot(wp.cross(b - a, c - a), d - a)


@wp.func
def segment_crosses_triangle(p: wp.vec3d, q: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d) -> bool:
    """Whether the closed segment pq meets the closed triangle abc (False when pq lies in its plane).

    Both ends within rounding of the plane (``COPLANAR`` of the volume scale) count as in it: coplanar
    faces of a CAD part, far apart, would otherwise cross by the rounding of their orientations' signs.
    """
    zero = wp.float64(0.0)
    sp = orient(a, b, c, p)
    sq = orient(a, b, c, q)
    area = wp.length(wp.cross(b - a, c - a))
    scale = area * wp.max(wp.length(p - a), wp.length(q - a)) * COPLANAR
    if (sp > zero and sq > zero) or (sp < zero and sq < zero) or (wp.abs(sp) <= scale and wp.abs(sq) <= scale):
        return False
    s0 = orient(p, q, a, b)
    s1 = orient(p, q, b, c)
    s2 = orient(p, q, c, a)
    positive = s0 >= zero and s1 >= zero and s2 >= zero
    negative = s0 <= zero and s1 <= zero and s2 <= zero
    return positive or negative


@wp.func
def triangles_cross(a0: wp.vec3d, a1: wp.vec3d, a2: wp.vec3d, b0: wp.vec3d, b1: wp.vec3d, b2: wp.vec3d) -> bool:
    """Whether two triangles with no shared corner intersect (six edge-triangle tests)."""
    return (
        segment_crosses_triangle(a0, a1, b0, b1, b2)
        or segment_crosses_triangle(a1, a2, b0, b1, b2)
        or segment_crosses_triangle(a2, a0, b0, b1, b2)
        or segment_crosses_triangle(b0, b1, a0, a1, a2)
        or segment_crosses_triangle(b1, b2, a0, a1, a2)
        or segment_crosses_triangle(b2, b0, a0, a1, a2)
    )


@wp.kernel
def count_intersections(
    mesh: wp.uint64,
    positions: wp.array(dtype=wp.vec3d),
    faces: wp.array(dtype=wp.vec3i),
    lowers: wp.array(dtype=wp.vec3),
    uppers: wp.array(dtype=wp.vec3),
    hits_out: wp.array(dtype=wp.int32),
):
    """For each face i, count the other faces that intersect it (the sum counts every pair twice)."""
    i = wp.tid()
    fi = faces[i]
    a0 = positions[fi[0]]
    a1 = positions[fi[1]]
    a2 = positions[fi[2]]
    query = wp.mesh_query_aabb(mesh, lowers[i], uppers[i])
    j = wp.int32(0)
    count = wp.int32(0)
    while wp.mesh_query_aabb_next(query, j):
        if j == i:
            continue
        fj = faces[j]
        shared = wp.int32(0)
        ka = wp.int32(-1)  # corner of i not shared (when exactly one corner is shared: the opposite edge)
        kb = wp.int32(-1)
        for r in range(3):
            for s in range(3):
                if fi[r] == fj[s]:
                    shared += 1
                    ka = r
                    kb = s
        b0 = positions[fj[0]]
        b1 = positions[fj[1]]
        b2 = positions[fj[2]]
        hit = False
        if shared == 0:
            hit = triangles_cross(a0, a1, a2, b0, b1, b2)
        elif shared == 1:
            pa = positions[fi[(ka + 1) % 3]]
            qa = positions[fi[(ka + 2) % 3]]
            pb = positions[fj[(kb + 1) % 3]]
            qb = positions[fj[(kb + 2) % 3]]
            hit = segment_crosses_triangle(pa, qa, b0, b1, b2) or segment_crosses_triangle(pb, qb, a0, a1, a2)
        if hit:
            count += 1
    hits_out[i] = count

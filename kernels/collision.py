"""Body-body and self collisions: collision points against tets, penalty response from the distance field.

Depth and direction: in a tet touching the body's surface, the depth of the point's rest position below the
dense surface at rest and the way out to its nearest point, carried to the tet's current shape
(:func:`kernels.surface.visible_depth`), plus the contact offset; where no dense surface is in reach, the depth
below the face the point moves out through (else the nearest) corrected by how far that face lies outside the
visible surface. Deep inside, the paper's interpolated distance field and rotated gradients.

Collision points: samples of each body's dense surface, embedded like its dense vertices (in a tet or a
quadratic tet's sub-tet), or a bare tet mesh's surface vertices and optional samples on its triangles. A point
``p`` inside tet ``t`` of another body (or of its own, outside ``t``'s one-ring) gets the penalty force
``f = a d g`` (Kondo & Kanai, after Fisher & Lin); the reaction ``-f`` goes to the nodes of the cell of ``t``
that holds ``p``, by its weights there, so momentum is conserved. Implicitly the contact is a spring along
``g`` between the point and its image: the row ``J`` of ``g . (x_p - x_t)`` adds ``dt^2 a J^T J`` to the
system matrix, applied matrix-free in CG's product (pairs of embedded points).
"""

import warp as wp

from .embedding import in_cell, interpolate, tet_weights
from .grid import warp_max_at
from .surface import (
    VisibleSurface,
    add_rotated_gradients,
    contact_offset,
    depth_above,
    exit_face,
    interpolate_directions,
    visible_depth,
)

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated


@wp.kernel
def accumulate_gradients(
    tets: wp.array(dtype=wp.vec4i),
    rotation: wp.array(dtype=wp.mat33),
    rest_grad: wp.array(dtype=wp.vec3),
    grad_out: wp.array(dtype=wp.vec3),
):
    """grad[v] += R_t g0[v] for each corner v of each tet t (zero ``grad_out`` first).

    The step does this in the elastic kernel, which has R_t at hand (``kernels.fem.elastic_forces_and_stiffness``).
    """
    e = wp.tid()
    add_rotated_gradients(tets[e], rotation[e], rest_grad, grad_out)


@wp.func
def adjacent(row_start: wp.array(dtype=wp.int32), cols: wp.array(dtype=wp.int32), a: int, b: int) -> bool:
    """True if vertices a and b share a tet (the larger is in the smaller's sorted row of the upper pattern)."""
    row = wp.min(a, b)
    col = wp.max(a, b)
    lo = row_start[row]
    hi = row_start[row + 1]
    while lo < hi:
        mid = (lo + hi) // 2
        c = cols[mid]
        if c == col:
            return True
        if c < col:
            lo = mid + 1
        else:
            hi = mid
    return False


@wp.func
def near_tet(
    row_start: wp.array(dtype=wp.int32), cols: wp.array(dtype=wp.int32), anchor: wp.vec3i, t: wp.vec4i
) -> bool:
    """True if any anchor vertex of a point is a corner of tet t or in the one-ring of one of its corners."""
    for k in range(3):
        a = anchor[k]
        if a >= 0:
            for c in range(4):
                if adjacent(row_start, cols, t[c], a):
                    return True
    return False


@wp.kernel
def collision_points(
    cells: wp.array(dtype=wp.vec4i),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    point_cell: wp.array(dtype=wp.int32),
    point_bary: wp.array(dtype=wp.vec4),
    point_body: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
    capacity: int,
    points_out: wp.array(dtype=wp.vec3),
    point_velocity_out: wp.array(dtype=wp.vec3),
    speed_max_out: wp.array(dtype=float),
    first_out: wp.array(dtype=wp.int32),
):
    """Collision point positions and velocities (interpolated like the dense mesh); per body the top speed.

    The speed is an atomic max per body, one per warp where the warp's points are one body's (the points are
    stored body after body), attempted only when above the value already there (:func:`kernels.grid.warp_max_at`).
    A late pass's (``first_out`` not empty): where its contacts start in the buffers, ``min(count, capacity)``.
    """
    i = wp.tid()
    t = cells[point_cell[i]]
    w = point_bary[i]
    points_out[i] = interpolate(x, t, w)
    u = interpolate(v, t, w)
    point_velocity_out[i] = u
    speed = wp.length(u)
    warp_max_at(speed, point_body[i], speed_max_out)
    if i == 0 and first_out.shape[0] > 0:
        first_out[0] = wp.min(count[0], capacity)


BLOCK_SYNC = r"""
#if defined(__CUDA_ARCH__)
__syncthreads();
#endif
"""


@wp.func_native(BLOCK_SYNC)
def block_sync():
    """Barrier of the threads of a block; their global writes before it are visible to all after it.

    Every thread of the block must reach it. A no-op on the CPU, where a block is one thread.
    """
    ...


@wp.func
def leaf_box(leaf: wp.vec4i, tets: wp.array(dtype=wp.vec4i), x: wp.array(dtype=wp.vec3)):
    """Bounding box of a leaf's tets (-1: none); empty (lower above upper) for a leaf without tets."""
    lo = wp.vec3(1.0e30)
    hi = wp.vec3(-1.0e30)
    for k in range(4):
        if leaf[k] >= 0:
            t = tets[leaf[k]]
            for c in range(4):
                lo = wp.min(lo, x[t[c]])
                hi = wp.max(hi, x[t[c]])
    return lo, hi


@wp.kernel
def refit_trees(
    # inputs
    tets: wp.array(dtype=wp.vec4i),
    x: wp.array(dtype=wp.vec3),
    body_tet_start: wp.array(dtype=wp.int32),
    node_start: wp.array(dtype=wp.int32),
    leaf_start: wp.array(dtype=wp.int32),
    leaf_tets: wp.array(dtype=wp.vec4i),
    threads: int,
    # outputs
    inverse_out: wp.array(dtype=wp.mat33),
    origin_out: wp.array(dtype=wp.vec3),
    node_lower_out: wp.array(dtype=wp.vec3),
    node_upper_out: wp.array(dtype=wp.vec3),
    body_lower_out: wp.array(dtype=wp.vec3),
    body_upper_out: wp.array(dtype=wp.vec3),
):
    """Per body (one block of ``threads`` threads): its tets' inverse edge matrices, first corners, tree boxes.

    The tree of body b is complete, in heap order (node k has children 2k+1 and 2k+2) from
    ``node_start[b]``, its L = ``leaf_start[b+1] - leaf_start[b]`` leaves last; the leaves are boxed from
    their tets' corners, then each level from the one below it, with a block barrier between levels. The
    root's box is the body's. A degenerate (flat) tet gets a zero inverse, which the inside test refuses.
    """
    body, lane = wp.tid()
    for e in range(body_tet_start[body] + lane, body_tet_start[body + 1], threads):
        t = tets[e]
        x0 = x[t[0]]
        A = wp.matrix_from_cols(x[t[1]] - x0, x[t[2]] - x0, x[t[3]] - x0)
        inverse_out[e] = wp.where(wp.abs(wp.determinant(A)) < 1.0e-20, wp.mat33(), wp.inverse(A))
        origin_out[e] = x0
    ns = node_start[body]
    ls = leaf_start[body]
    first_leaf = leaf_start[body + 1] - ls - 1
    for j in range(lane, first_leaf + 1, threads):
        lo, hi = leaf_box(leaf_tets[ls + j], tets, x)
        node_lower_out[ns + first_leaf + j] = lo
        node_upper_out[ns + first_leaf + j] = hi
    block_sync()
    end = first_leaf
    while end > 0:
        begin = (end - 1) // 2
        for k in range(begin + lane, end, threads):
            a = ns + 2 * k + 1
            node_lower_out[ns + k] = wp.min(node_lower_out[a], node_lower_out[a + 1])
            node_upper_out[ns + k] = wp.max(node_upper_out[a], node_upper_out[a + 1])
        block_sync()
        end = begin
    if lane == 0:
        body_lower_out[body] = node_lower_out[ns]
        body_upper_out[body] = node_upper_out[ns]


@wp.func
def leaf_holds(
    q: wp.vec3,
    leaf: wp.vec4i,
    tet_inverse: wp.array(dtype=wp.mat33),
    tet_origin: wp.array(dtype=wp.vec3),
    tet_slack: wp.array(dtype=float),
) -> int:
    """Bit k set if the leaf's k-th tet holds ``q``, its weights there no lower than minus the tet's slack.

    A flat tet, with a zero inverse, holds nothing. The four tets' loads do not depend on one another, so
    they are in flight together.
    """
    mask = int(0)
    for k in range(4):
        e = wp.max(leaf[k], 0)
        inverse = tet_inverse[e]
        w = tet_weights(q, inverse, tet_origin[e])
        if leaf[k] >= 0 and wp.min(w) >= -tet_slack[e] and wp.determinant(inverse) != 0.0:
            mask = mask | (1 << k)
    return mask


@wp.struct
class Found:
    """The contacts found: per contact the point, the cell, its weights there, the way out, the depth (m).

    ``count[0]`` counts every contact found (past the buffers' length dropped); ``deepest[0]``: the largest depth.
    """

    count: wp.array(dtype=wp.int32)
    point: wp.array(dtype=wp.int32)
    cell: wp.array(dtype=wp.int32)
    bary: wp.array(dtype=wp.vec4)
    normal: wp.array(dtype=wp.vec3)
    depth: wp.array(dtype=float)
    deepest: wp.array(dtype=float)


@wp.func
def depth_in_tet(
    p: int,
    q: wp.vec3,
    e: int,
    t: wp.vec4i,
    w: wp.vec4,
    same: bool,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    dt: float,
    tet_face_start: wp.array(dtype=wp.int32),
    tet_faces: wp.array(dtype=wp.vec3i),
    tet_face_ids: wp.array(dtype=wp.int32),
    face_depth: wp.array(dtype=float),
    surface: VisibleSurface,
    point_velocity: wp.array(dtype=wp.vec3),
    point_anchor: wp.array(dtype=wp.vec3i),
    row_start: wp.array(dtype=wp.int32),
    cols: wp.array(dtype=wp.int32),
    depth: wp.array(dtype=float),
    grad: wp.array(dtype=wp.vec3),
):
    """Depth and direction of point p (at q, weights w in tet e, which holds it), and what they are.

    Returns ``(status, d, g, bound)``: 0, the point refused (its own body's, ``same``, in its anchors' one-ring);
    1, ``d``, ``g`` answer; 2, the tet touches a dense surface: :func:`kernels.surface.visible_depth` answers
    after the walk (``d``, ``g`` where it finds nothing in reach), ``bound`` (:func:`depth_above`) bounding its
    query; 3, surely outside that surface by more than its body's contact offset: no contact, no query.
    """
    d = float(0.0)
    g = wp.vec3()
    if same:
        if near_tet(row_start, cols, point_anchor[p], t):
            return 0, d, g, 0.0
    f0 = tet_face_start[e]
    f1 = tet_face_start[e + 1]
    if f1 > f0:
        # near the surface: below the face the point leaves through (docs/decisions.md, "The face a point came
        # in through")
        step = dt * (point_velocity[p] - interpolate(v, t, w))
        d, g, _margin, f_near = exit_face(x, face_depth, tet_face_ids, tet_faces, f0, f1, q, step)
        b = surface.tet_body[e]
        if surface.mesh[b] != wp.uint64(0):
            rest_q = interpolate(surface.rest_x, t, w)
            bound = depth_above(surface.rest_x, face_depth, tet_faces[f_near], tet_face_ids[f_near], rest_q)
            if bound + surface.offset < 0.0:
                return 3, d, g, bound
            return 2, d, g, bound
        return 1, d, g, 0.0
    # deep inside: the paper's interpolated distance field and rotated gradients
    d = w[0] * depth[t[0]] + w[1] * depth[t[1]] + w[2] * depth[t[2]] + w[3] * depth[t[3]]
    return 1, d, interpolate_directions(grad, t, w), 0.0


@wp.func
def store_contact(
    p: int,
    e: int,
    t: wp.vec4i,
    w: wp.vec4,
    d: float,
    g: wp.vec3,
    v: wp.array(dtype=wp.vec3),
    point_velocity: wp.array(dtype=wp.vec3),
    dt: float,
    found_out: Found,
    late: int,
) -> bool:
    """Records point p's contact with cell e (nodes t, weights w) if its depth ``d`` is positive; returns if it did.

    A ``late`` contact is found at the positions a solve predicts (``v`` its answer): it records the depth
    at the step's start that the linearised contact implies, ``d + dt g . u`` (negative where the point was
    still outside), and leaves the depth statistics alone.
    """
    if d <= 0.0 or wp.length(g) == 0.0:
        return False
    n = wp.normalize(g)
    kept = d
    if late != 0:
        kept = d + dt * wp.dot(n, point_velocity[p] - interpolate(v, t, w))
    else:
        wp.atomic_max(found_out.deepest, 0, d)
    slot = wp.atomic_add(found_out.count, 0, 1)
    if slot < found_out.point.shape[0]:
        found_out.point[slot] = p
        found_out.cell[slot] = e
        found_out.bary[slot] = w
        found_out.normal[slot] = n
        found_out.depth[slot] = kept
    return True


@wp.func
def answer_pending(
    p: int,
    q: wp.vec3,
    e: int,
    w: wp.vec4,
    same: bool,
    status: int,
    d: float,
    g: wp.vec3,
    bound: float,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    dt: float,
    tets: wp.array(dtype=wp.vec4i),
    cells: wp.array(dtype=wp.vec4i),
    tet_face_start: wp.array(dtype=wp.int32),
    tet_faces: wp.array(dtype=wp.vec3i),
    tet_face_ids: wp.array(dtype=wp.int32),
    face_depth: wp.array(dtype=float),
    surface: VisibleSurface,
    point_velocity: wp.array(dtype=wp.vec3),
    point_anchor: wp.array(dtype=wp.vec3i),
    row_start: wp.array(dtype=wp.int32),
    cols: wp.array(dtype=wp.int32),
    depth: wp.array(dtype=float),
    grad: wp.array(dtype=wp.vec3),
    found_out: Found,
    late: int,
):
    """Records point p's contact with tet e (at q, weights w) as :func:`walk_tree` answered it.

    Status 1: ``d``, ``g``; 2: :func:`kernels.surface.visible_depth`'s; 3: none. It goes to the cell holding
    the point (:func:`in_cell`); in a quadratic tet the answer is asked again at the material point there.
    """
    t = tets[e]
    c, mu, lam = in_cell(q, e, t, w, x, cells, surface.rest_x, surface.dm_inv)
    if cells.shape[0] != tets.shape[0]:
        status, d, g, bound = depth_in_tet(
            p, q, e, t, lam, same, x, v, dt, tet_face_start, tet_faces, tet_face_ids, face_depth, surface,
            point_velocity, point_anchor, row_start, cols, depth, grad,
        )  # fmt: skip
    if status == 2:
        d, g = visible_depth(surface, x, e, t, lam, d, g, bound, contact_offset(p, e, t, lam, q, x, v, dt,
            tet_face_start, tet_faces, tet_face_ids, face_depth, surface, point_velocity))  # fmt: skip
    if status == 1 or status == 2:
        store_contact(
            p, c, cells[c], mu, d, g, v, point_velocity, dt, found_out, late,
        )  # fmt: skip


@wp.func
def overlaps(q: wp.vec3, lo: wp.vec3, hi: wp.vec3) -> bool:
    """Whether point q lies in the box [lo, hi]."""
    return q[0] >= lo[0] and q[1] >= lo[1] and q[2] >= lo[2] and q[0] <= hi[0] and q[1] <= hi[1] and q[2] <= hi[2]


@wp.func
def group_holds(
    q: wp.vec3, node_lower: wp.array(dtype=wp.vec3), node_upper: wp.array(dtype=wp.vec3), base: int, size: int
) -> int:
    """Bit j set if box ``base + j`` holds ``q``, for the ``size`` (at most 8) consecutive boxes from ``base``.

    The boxes' loads do not depend on one another, so they are in flight together.
    """
    mask = int(0)
    for j in range(8):
        k = base + wp.min(j, size - 1)
        if j < size and overlaps(q, node_lower[k], node_upper[k]):
            mask = mask | (1 << j)
    return mask


@wp.func
def lowest_bit(mask: int) -> int:
    """Index of the lowest set bit of a nonzero mask."""
    j = int(0)
    while (mask >> j) & 1 == 0:
        j += 1
    return j


LATE_BY_POINT = wp.constant(1)
"""A late look that leaves out every point with a contact this step."""

LATE_BY_PAIR = wp.constant(2)
"""A late look that leaves out only the (point, body) pair of a point's one contact this step, and a point with
contacts with more than one body: a point touching one body still finds another it is carried into."""

WALK_STRIDE = wp.constant(3)
"""Tree levels a walk descends at a time: it tests 2^3 = 8 boxes at once (the grandchildren's children)."""


@wp.func
def walk_tree(
    p: int,
    q: wp.vec3,
    body: int,
    same: bool,
    node_start: wp.array(dtype=wp.int32),
    leaf_start: wp.array(dtype=wp.int32),
    leaf_tets: wp.array(dtype=wp.vec4i),
    node_lower: wp.array(dtype=wp.vec3),
    node_upper: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    dt: float,
    tets: wp.array(dtype=wp.vec4i),
    tet_inverse: wp.array(dtype=wp.mat33),
    tet_origin: wp.array(dtype=wp.vec3),
    tet_slack: wp.array(dtype=float),
    tet_face_start: wp.array(dtype=wp.int32),
    tet_faces: wp.array(dtype=wp.vec3i),
    tet_face_ids: wp.array(dtype=wp.int32),
    face_depth: wp.array(dtype=float),
    surface: VisibleSurface,
    point_velocity: wp.array(dtype=wp.vec3),
    point_anchor: wp.array(dtype=wp.vec3i),
    row_start: wp.array(dtype=wp.int32),
    cols: wp.array(dtype=wp.int32),
    depth: wp.array(dtype=float),
    grad: wp.array(dtype=wp.vec3),
):
    """Point p (at q) against one body's tet tree: at most one contact (see :func:`detect_contacts`).

    Depth first, :data:`WALK_STRIDE` levels at a time: the 8 boxes three levels below a box that holds the
    point are tested together (one round trip to memory), the bits of those that hold it kept 8 to a level in
    an int64 stack (the first step down takes 1 to 3 levels). A leaf's four tets are tested together; the
    first that answers (:func:`depth_in_tet`: a positive depth, or status 2) ends the walk. A tet whose part
    of the dense surface the point surely lies outside (status 3) does not: where parts of a body overlap
    (one pressed onto another), the point may lie in the cage margin of one and inside the other. Returns the
    tet that answered (-1 if none), its weights and the answer, for :func:`answer_pending` to record.
    """
    ns = node_start[body]
    ls = leaf_start[body]
    leaves = leaf_start[body + 1] - ls
    leaf_level = int(0)
    while (1 << leaf_level) < leaves:
        leaf_level += 1
    top = wp.where(leaf_level == 0, 0, leaf_level - WALK_STRIDE * ((leaf_level - 1) // WALK_STRIDE))
    level = top  # tree level of the group of boxes being walked
    base = (1 << top) - 1  # its first node
    mask = group_holds(q, node_lower, node_upper, ns + base, 1 << top)
    stack = wp.int64(0)
    found = bool(False)
    pending = int(-1)
    pending_w = wp.vec4()
    pending_status = int(0)
    pending_d = float(0.0)
    pending_g = wp.vec3()
    pending_bound = float(0.0)
    while not found and (mask != 0 or level > top):
        if mask == 0:
            # the group is done: back to the group of its parent (its 8 aligned siblings, or the whole
            # top level, which has at most 8 nodes), and what was left of it
            parent = ((base + 1) >> WALK_STRIDE) - 1
            level -= WALK_STRIDE
            first = (1 << level) - 1
            base = first + (((parent - first) >> WALK_STRIDE) << WALK_STRIDE)
            mask = int(stack & wp.int64(255))
            stack = stack >> wp.int64(8)
        else:
            node = base + lowest_bit(mask)
            mask = mask & (mask - 1)
            if level == leaf_level:
                leaf = leaf_tets[ls + node - (leaves - 1)]
                inside = leaf_holds(q, leaf, tet_inverse, tet_origin, tet_slack)
                while inside != 0 and not found:
                    k = lowest_bit(inside)
                    inside = inside & (inside - 1)
                    e = leaf[k]
                    t = tets[e]
                    w = tet_weights(q, tet_inverse[e], tet_origin[e])
                    status, d, g, bound = depth_in_tet(
                        p, q, e, t, w, same, x, v, dt, tet_face_start, tet_faces, tet_face_ids, face_depth,
                        surface, point_velocity, point_anchor, row_start, cols, depth, grad,
                    )  # fmt: skip
                    if status == 2 or (status == 1 and d > 0.0 and wp.length(g) > 0.0):
                        found = True
                        pending = e
                        pending_w = w
                        pending_status = status
                        pending_d = d
                        pending_g = g
                        pending_bound = bound
            else:
                stack = (stack << wp.int64(8)) | wp.int64(mask)
                level += WALK_STRIDE
                base = ((node + 1) << WALK_STRIDE) - 1
                mask = group_holds(q, node_lower, node_upper, ns + base, 8)
    return pending, pending_w, pending_status, pending_d, pending_g, pending_bound


@wp.kernel
def detect_contacts(
    # inputs: geometry
    body_bvh: wp.uint64,
    node_start: wp.array(dtype=wp.int32),
    leaf_start: wp.array(dtype=wp.int32),
    leaf_tets: wp.array(dtype=wp.vec4i),
    node_lower: wp.array(dtype=wp.vec3),
    node_upper: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    dt: float,
    tets: wp.array(dtype=wp.vec4i),
    cells: wp.array(dtype=wp.vec4i),
    tet_inverse: wp.array(dtype=wp.mat33),
    tet_origin: wp.array(dtype=wp.vec3),
    tet_slack: wp.array(dtype=float),
    tet_face_start: wp.array(dtype=wp.int32),
    tet_faces: wp.array(dtype=wp.vec3i),
    tet_face_ids: wp.array(dtype=wp.int32),
    face_depth: wp.array(dtype=float),
    surface: VisibleSurface,
    points: wp.array(dtype=wp.vec3),
    point_velocity: wp.array(dtype=wp.vec3),
    point_body: wp.array(dtype=wp.int32),
    point_anchor: wp.array(dtype=wp.vec3i),
    body_self: wp.array(dtype=wp.int32),
    row_start: wp.array(dtype=wp.int32),
    cols: wp.array(dtype=wp.int32),
    depth: wp.array(dtype=float),
    grad: wp.array(dtype=wp.vec3),
    lanes: int,
    point_contact: wp.array(dtype=wp.int32),
    late: int,
    # outputs
    found_out: Found,
):
    """Per collision point and body whose box holds it: that body's tet tree, at most one contact.

    The body BVH gives the bodies the point may collide with (another body, or its own if that collides
    with itself) and only their trees are walked (:func:`walk_tree`), so a point never walks the tets of its
    own body, which it lies among, unless that body collides with itself. ``lanes`` threads share a point,
    each walking every ``lanes``-th of its bodies, since a point in a pile may lie in several bodies' boxes.
    Each contact goes to ``found_out`` (:class:`Found`). A late look (``late``, :data:`LATE_BY_POINT` or
    :data:`LATE_BY_PAIR`) leaves out what ``point_contact`` marks (``kernels.contacts.mark_contact``).
    """
    tid = wp.tid()
    p = tid // lanes
    lane = tid - p * lanes
    touched = int(-1)  # the one body whose contact with p this step has (a late look by pairs leaves it out)
    if late != 0:
        mark = point_contact[p]
        if mark < 0 or (mark > 0 and late == LATE_BY_POINT):
            return
        touched = mark - 1
    q = points[p]
    body_p = point_body[p]
    self_ok = body_self[body_p] != 0
    bodies = wp.bvh_query_aabb(body_bvh, q, q)
    body = int(0)
    candidate = int(-1)
    while wp.bvh_query_next(bodies, body):
        candidate += 1
        same = body == body_p
        if candidate % lanes != lane or (same and not self_ok) or body == touched:
            continue
        e, w, status, d, g, bound = walk_tree(
            p, q, body, same, node_start, leaf_start, leaf_tets, node_lower, node_upper, x, v, dt, tets,
            tet_inverse, tet_origin, tet_slack, tet_face_start, tet_faces, tet_face_ids, face_depth, surface,
            point_velocity, point_anchor, row_start, cols, depth, grad,
        )  # fmt: skip
        if e >= 0:
            answer_pending(
                p, q, e, w, same, status, d, g, bound, x, v, dt, tets, cells, tet_face_start, tet_faces,
                tet_face_ids, face_depth, surface, point_velocity, point_anchor, row_start, cols, depth, grad,
                found_out, late,
            )  # fmt: skip


@wp.kernel
def detect_contacts_direct(
    # inputs: geometry
    body_lower: wp.array(dtype=wp.vec3),
    body_upper: wp.array(dtype=wp.vec3),
    node_start: wp.array(dtype=wp.int32),
    leaf_start: wp.array(dtype=wp.int32),
    leaf_tets: wp.array(dtype=wp.vec4i),
    node_lower: wp.array(dtype=wp.vec3),
    node_upper: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    dt: float,
    tets: wp.array(dtype=wp.vec4i),
    cells: wp.array(dtype=wp.vec4i),
    tet_inverse: wp.array(dtype=wp.mat33),
    tet_origin: wp.array(dtype=wp.vec3),
    tet_slack: wp.array(dtype=float),
    tet_face_start: wp.array(dtype=wp.int32),
    tet_faces: wp.array(dtype=wp.vec3i),
    tet_face_ids: wp.array(dtype=wp.int32),
    face_depth: wp.array(dtype=float),
    surface: VisibleSurface,
    points: wp.array(dtype=wp.vec3),
    point_velocity: wp.array(dtype=wp.vec3),
    point_body: wp.array(dtype=wp.int32),
    point_anchor: wp.array(dtype=wp.vec3i),
    body_self: wp.array(dtype=wp.int32),
    row_start: wp.array(dtype=wp.int32),
    cols: wp.array(dtype=wp.int32),
    depth: wp.array(dtype=float),
    grad: wp.array(dtype=wp.vec3),
    lanes: int,
    point_contact: wp.array(dtype=wp.int32),
    late: int,
    # outputs
    found_out: Found,
):
    """:func:`detect_contacts` for a scene of few bodies: each point tests every body's box itself.

    No body BVH to refit or query (whose traversal stack takes shared memory in every block); the candidates
    are the bodies in index order, shared among ``lanes`` threads as there.
    """
    tid = wp.tid()
    p = tid // lanes
    lane = tid - p * lanes
    if late != 0 and point_contact[p] != 0:
        return
    q = points[p]
    body_p = point_body[p]
    self_ok = body_self[body_p] != 0
    candidate = int(-1)
    for body in range(body_lower.shape[0]):
        if overlaps(q, body_lower[body], body_upper[body]):
            candidate += 1
            same = body == body_p
            if candidate % lanes == lane and (self_ok or not same):
                e, w, status, d, g, bound = walk_tree(
                    p, q, body, same, node_start, leaf_start, leaf_tets, node_lower, node_upper, x, v, dt, tets,
                    tet_inverse, tet_origin, tet_slack, tet_face_start, tet_faces, tet_face_ids, face_depth, surface,
                    point_velocity, point_anchor, row_start, cols, depth, grad,
                )  # fmt: skip
                if e >= 0:
                    answer_pending(
                        p, q, e, w, same, status, d, g, bound, x, v, dt, tets, cells, tet_face_start, tet_faces,
                        tet_face_ids, face_depth, surface, point_velocity, point_anchor, row_start, cols, depth,
                        grad, found_out, late,
                    )  # fmt: skip


@wp.kernel
def detect_carried(
    # inputs: the contacts carried over from the step before
    carried_count: wp.array(dtype=wp.int32),
    carried_point: wp.array(dtype=wp.int32),
    carried_cell: wp.array(dtype=wp.int32),
    cell_body: wp.array(dtype=wp.int32),
    # inputs: geometry
    node_start: wp.array(dtype=wp.int32),
    leaf_start: wp.array(dtype=wp.int32),
    leaf_tets: wp.array(dtype=wp.vec4i),
    node_lower: wp.array(dtype=wp.vec3),
    node_upper: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    dt: float,
    tets: wp.array(dtype=wp.vec4i),
    cells: wp.array(dtype=wp.vec4i),
    tet_inverse: wp.array(dtype=wp.mat33),
    tet_origin: wp.array(dtype=wp.vec3),
    tet_slack: wp.array(dtype=float),
    tet_face_start: wp.array(dtype=wp.int32),
    tet_faces: wp.array(dtype=wp.vec3i),
    tet_face_ids: wp.array(dtype=wp.int32),
    face_depth: wp.array(dtype=float),
    surface: VisibleSurface,
    points: wp.array(dtype=wp.vec3),
    point_velocity: wp.array(dtype=wp.vec3),
    point_body: wp.array(dtype=wp.int32),
    point_anchor: wp.array(dtype=wp.vec3i),
    row_start: wp.array(dtype=wp.int32),
    cols: wp.array(dtype=wp.int32),
    depth: wp.array(dtype=float),
    grad: wp.array(dtype=wp.vec3),
    # outputs
    found_out: Found,
):
    """:func:`detect_contacts` for the (point, body) pairs of the step before's contacts only.

    Each carried contact's point walks the tree of the body it touched, at the positions the collision points
    now have; a pair the step before did not have waits for the step's late look.
    """
    i = wp.tid()
    if i >= wp.min(carried_count[0], carried_point.shape[0]):
        return
    p = carried_point[i]
    body = cell_body[carried_cell[i]]
    q = points[p]
    same = body == point_body[p]
    e, w, status, d, g, bound = walk_tree(
        p, q, body, same, node_start, leaf_start, leaf_tets, node_lower, node_upper, x, v, dt, tets, tet_inverse,
        tet_origin, tet_slack, tet_face_start, tet_faces, tet_face_ids, face_depth, surface, point_velocity,
        point_anchor, row_start, cols, depth, grad,
    )  # fmt: skip
    if e >= 0:
        answer_pending(
            p, q, e, w, same, status, d, g, bound, x, v, dt, tets, cells, tet_face_start, tet_faces, tet_face_ids,
            face_depth, surface, point_velocity, point_anchor, row_start, cols, depth, grad, found_out, 0,
        )  # fmt: skip


@wp.kernel
def keep_contacts(
    count: wp.array(dtype=wp.int32),
    contact_point: wp.array(dtype=wp.int32),
    contact_cell: wp.array(dtype=wp.int32),
    carried_count: wp.array(dtype=wp.int32),
    carried_point: wp.array(dtype=wp.int32),
    carried_cell: wp.array(dtype=wp.int32),
):
    """Copies the step's contacts (point, cell) for the next step's :func:`detect_carried`."""
    i = wp.tid()
    n = wp.min(count[0], contact_point.shape[0])
    if i == 0:
        carried_count[0] = n
    if i < n:
        carried_point[i] = contact_point[i]
        carried_cell[i] = contact_cell[i]

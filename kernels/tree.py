"""The per-body tet trees that contact detection walks: their refit each step, and box tests on them.

Each body's tree is complete, in heap order, over leaves of four tets; a refit boxes the leaves from their
tets' corners and each level from the one below it.
"""

import warp as wp

from .embedding import tet_weights

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
    v: wp.array(dtype=wp.vec3),
    margin: wp.array(dtype=float),
    threads: int,
    # outputs
    inverse_out: wp.array(dtype=wp.mat33),
    origin_out: wp.array(dtype=wp.vec3),
    node_lower_out: wp.array(dtype=wp.vec3),
    node_upper_out: wp.array(dtype=wp.vec3),
    body_lower_out: wp.array(dtype=wp.vec3),
    body_upper_out: wp.array(dtype=wp.vec3),
    body_speed_out: wp.array(dtype=float),
):
    """Per body (one block of ``threads`` threads): its tets' inverse edge matrices, first corners, tree boxes.

    The tree of body b is complete, in heap order (node k has children 2k+1 and 2k+2) from
    ``node_start[b]``, its L = ``leaf_start[b+1] - leaf_start[b]`` leaves last; the leaves are boxed from
    their tets' corners, then each level from the one below it, with a block barrier between levels. The
    root's box is the body's. A degenerate (flat) tet gets a zero inverse, which the inside test refuses.
    With ``margin`` (per body, m; empty: none) every box is grown by the body's margin on each side. Per
    body, the fastest speed (m/s) in ``v`` among its tets' corners goes to ``body_speed_out``.
    """
    body, lane = wp.tid()
    if lane == 0:
        body_speed_out[body] = 0.0
    block_sync()
    grow = float(0.0)
    if margin.shape[0] > 0:
        grow = margin[body]
    speed = float(0.0)
    for e in range(body_tet_start[body] + lane, body_tet_start[body + 1], threads):
        t = tets[e]
        for c in range(4):
            speed = wp.max(speed, wp.length(v[t[c]]))
        x0 = x[t[0]]
        A = wp.matrix_from_cols(x[t[1]] - x0, x[t[2]] - x0, x[t[3]] - x0)
        inverse_out[e] = wp.where(wp.abs(wp.determinant(A)) < 1.0e-20, wp.mat33(), wp.inverse(A))
        origin_out[e] = x0
    ns = node_start[body]
    ls = leaf_start[body]
    first_leaf = leaf_start[body + 1] - ls - 1
    for j in range(lane, first_leaf + 1, threads):
        lo, hi = leaf_box(leaf_tets[ls + j], tets, x)
        node_lower_out[ns + first_leaf + j] = lo - wp.vec3(grow)
        node_upper_out[ns + first_leaf + j] = hi + wp.vec3(grow)
    wp.atomic_max(body_speed_out, body, speed)
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
) -> int:
    """Bit k set if the leaf's k-th tet holds ``q`` (a flat tet, with a zero inverse, holds nothing).

    The four tets' loads do not depend on one another, so they are in flight together.
    """
    mask = int(0)
    for k in range(4):
        e = wp.max(leaf[k], 0)
        inverse = tet_inverse[e]
        w = tet_weights(q, inverse, tet_origin[e])
        if leaf[k] >= 0 and wp.min(w) >= 0.0 and wp.determinant(inverse) != 0.0:
            mask = mask | (1 << k)
    return mask


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

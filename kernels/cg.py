"""Block-Jacobi preconditioned conjugate gradients on a 3x3-block CSR matrix, as fused kernels.

One iteration is four launches: ``cg_spmv`` (q = A p fused with p.q), ``cg_update_xr`` (x, r, z fused
with r.z), ``cg_update_p`` and the single-thread ``cg_advance``. Dot products are reduced per block
(a tile sum, then one atomic add per block): one global atomic per thread is several times slower at a
million rows. The reducing kernels are launched over ``n`` rounded up to whole blocks and take ``n``.
All per-iteration scalars live in device arrays indexed by the device-side iteration counter, so the
loop needs no host synchronisation and can be captured in a CUDA graph with ``wp.capture_while``. Rows
with ``free == 0`` (pinned vertices) are held at their initial value: their residual and search
direction stay zero.
"""

import warp as wp


@wp.func
def spmv_row(
    row_start: wp.array(dtype=wp.int32),
    cols: wp.array(dtype=wp.int32),
    values: wp.array(dtype=wp.mat33),
    p: wp.array(dtype=wp.vec3),
    i: int,
) -> wp.vec3:
    """Row ``i`` of the block product A p."""
    acc = wp.vec3()
    for j in range(row_start[i], row_start[i + 1]):
        acc += values[j] * p[cols[j]]
    return acc


@wp.func
def block_sum(value: float, total_out: wp.array(dtype=float), index: int):
    """Add ``value`` of every thread of the block into ``total_out[index]``: one atomic per block.

    A cooperative tile reduction (every thread of the block must reach it); on the CPU a block is one
    thread, so it is a plain atomic add.
    """
    wp.tile_atomic_add(total_out, wp.tile_sum(wp.tile(value)), offset=index)


@wp.kernel
def cg_init(
    # inputs: system
    n: int,
    row_start: wp.array(dtype=wp.int32),
    cols: wp.array(dtype=wp.int32),
    values: wp.array(dtype=wp.mat33),
    diag_inv: wp.array(dtype=wp.mat33),
    free: wp.array(dtype=wp.int32),
    b: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    extra_ax: wp.array(dtype=wp.vec3),
    has_extra: int,
    # outputs
    r_out: wp.array(dtype=wp.vec3),
    z_out: wp.array(dtype=wp.vec3),
    p_out: wp.array(dtype=wp.vec3),
    rz_out: wp.array(dtype=float),
    bz_out: wp.array(dtype=float),
):
    """r = b - A x (A x plus extra_ax, its matrix-free part), z = M^-1 r, p = z; r.z into rz[0], b.M^-1 b to bz[0]."""
    i = wp.tid()
    rz = float(0.0)
    bz = float(0.0)
    if i < n:
        r = wp.vec3()
        z = wp.vec3()
        if free[i] != 0:
            r = b[i] - spmv_row(row_start, cols, values, x, i)
            if has_extra != 0:
                r -= extra_ax[i]
            z = diag_inv[i] * r
            rz = wp.dot(r, z)
            bz = wp.dot(b[i], diag_inv[i] * b[i])
        r_out[i] = r
        z_out[i] = z
        p_out[i] = z
    block_sum(rz, rz_out, 0)
    block_sum(bz, bz_out, 0)


@wp.kernel
def cg_start(
    rz: wp.array(dtype=float),
    bz: wp.array(dtype=float),
    tolerance: wp.array(dtype=float),
    max_iterations: wp.array(dtype=wp.int32),
    iteration_out: wp.array(dtype=wp.int32),
    cond_out: wp.array(dtype=wp.int32),
):
    """Single thread: resets the iteration counter and decides whether to iterate at all."""
    iteration_out[0] = 0
    tol = tolerance[0]
    go = 0
    if max_iterations[0] > 0 and rz[0] > tol * tol * bz[0] and rz[0] > 0.0:
        go = 1
    cond_out[0] = go


@wp.kernel
def cg_spmv(
    n: int,
    row_start: wp.array(dtype=wp.int32),
    cols: wp.array(dtype=wp.int32),
    values: wp.array(dtype=wp.mat33),
    free: wp.array(dtype=wp.int32),
    p: wp.array(dtype=wp.vec3),
    iteration: wp.array(dtype=wp.int32),
    extra_q: wp.array(dtype=wp.vec3),
    has_extra: int,
    q_out: wp.array(dtype=wp.vec3),
    pq_out: wp.array(dtype=float),
):
    """q = A p (+ extra_q, a matrix-free part computed before) on free rows, zero on pinned rows; p.q into pq[k]."""
    i = wp.tid()
    pq = float(0.0)
    if i < n:
        q = wp.vec3()
        if free[i] != 0:
            q = spmv_row(row_start, cols, values, p, i)
            if has_extra != 0:
                q += extra_q[i]
            pq = wp.dot(p[i], q)
        q_out[i] = q
    block_sum(pq, pq_out, iteration[0])


@wp.kernel
def cg_update_xr(
    n: int,
    diag_inv: wp.array(dtype=wp.mat33),
    p: wp.array(dtype=wp.vec3),
    q: wp.array(dtype=wp.vec3),
    iteration: wp.array(dtype=wp.int32),
    pq: wp.array(dtype=float),
    rz: wp.array(dtype=float),
    x_out: wp.array(dtype=wp.vec3),
    r_out: wp.array(dtype=wp.vec3),
    z_out: wp.array(dtype=wp.vec3),
    rz_out: wp.array(dtype=float),
):
    """x += alpha p, r -= alpha q, z = M^-1 r with alpha = rz[k] / pq[k]; accumulates r.z into rz[k+1]."""
    i = wp.tid()
    k = iteration[0]
    rz_next = float(0.0)
    if i < n:
        denom = pq[k]
        alpha = float(0.0)
        if denom > 0.0:
            alpha = rz[k] / denom
        x_out[i] = x_out[i] + alpha * p[i]
        r = r_out[i] - alpha * q[i]
        z = diag_inv[i] * r
        r_out[i] = r
        z_out[i] = z
        rz_next = wp.dot(r, z)
    block_sum(rz_next, rz_out, k + 1)


@wp.kernel
def cg_update_p(
    z: wp.array(dtype=wp.vec3),
    iteration: wp.array(dtype=wp.int32),
    rz: wp.array(dtype=float),
    p_out: wp.array(dtype=wp.vec3),
):
    """p = z + beta p with beta = rz[k+1] / rz[k]."""
    i = wp.tid()
    k = iteration[0]
    beta = 0.0
    if rz[k] > 0.0:
        beta = rz[k + 1] / rz[k]
    p_out[i] = z[i] + beta * p_out[i]


@wp.kernel
def cg_advance(
    rz: wp.array(dtype=float),
    pq: wp.array(dtype=float),
    bz: wp.array(dtype=float),
    tolerance: wp.array(dtype=float),
    max_iterations: wp.array(dtype=wp.int32),
    iteration_out: wp.array(dtype=wp.int32),
    cond_out: wp.array(dtype=wp.int32),
):
    """Single thread: k += 1; keep going while k < max, the residual is above tolerance and p.q > 0."""
    k = iteration_out[0]
    tol = tolerance[0]
    go = 0
    if k + 1 < max_iterations[0] and rz[k + 1] > tol * tol * bz[0] and pq[k] > 0.0:
        go = 1
    iteration_out[0] = k + 1
    cond_out[0] = go


@wp.kernel
def cg_finish(
    rz: wp.array(dtype=float),
    bz: wp.array(dtype=float),
    iteration: wp.array(dtype=wp.int32),
    counts_out: wp.array(dtype=wp.int32),
    residual_max_out: wp.array(dtype=float),
):
    """Single thread: counts the solve and its iterations (counts[0], counts[1]); keeps the largest residual."""
    k = iteration[0]
    counts_out[0] = counts_out[0] + 1
    counts_out[1] = counts_out[1] + k
    res = 0.0
    if bz[0] > 0.0:
        res = wp.sqrt(wp.max(rz[k], 0.0) / bz[0])
    residual_max_out[0] = wp.max(residual_max_out[0], res)

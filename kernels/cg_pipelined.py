"""Pipelined block-Jacobi PCG in one persistent launch: one grid barrier per iteration.

Chronopoulos-Gear PCG (:mod:`warpfem.kernels.cg`) needs two grid barriers per iteration: the product w = A u
reads u of other rows, and u.w, which the step sizes need, is a sum over all rows. Ghysels and Vanroose's
pipelined PCG reorders the recurrences so that both are taken from vectors known before the product: each
iteration reduces gamma = r.u and delta = w.u and publishes m = M^-1 w at the same barrier, then computes
n = A m and updates every vector by recurrences (z = n + beta z, q = m + beta q, s = w + beta s,
p = u + beta p, x += alpha p, r -= alpha s, u -= alpha q, w -= alpha z): one barrier instead of two. The
product avoids a second barrier by ownership: each block owns a contiguous run of rows and every chunk of
those rows' gathered product (see ``warpfem.cg.CGSolver``), and sums them in shared memory
(:func:`block_accumulate`), so only the block's own threads meet before a row is updated. Contact pairs
add to the rows they touch in each block that owns one of them (each such block reads the pair's eight
values of m: a little work twice, no atomic add across blocks).

The recurrences drift from the true residual in float32 (on paper scene A's systems the pipelined iteration
stalled at a true relative residual of 3e-3 to 6e-3 against 1e-4 asked, scratch NumPy experiment), so every
``replace_every`` iterations r = b - A x, u = M^-1 r and w = A u are recomputed (two more barriers): with
every 25 the iteration counts matched Chronopoulos-Gear's within one and the true residual met 1e-4.

On CUDA each thread holds one chunk and up to two contact pairs in registers, and its row's eight vectors
(:class:`RowState`); on the CPU the launch is one thread, which walks everything and keeps the vectors in
arrays. The start (x moved along the given direction, r, u) is the one of ``cg_solve``.
"""

import warp as wp
from warpfem.kernels.cg import init_row, line_step, project_row, step_sizes
from warpfem.kernels.grid import block_accumulate, block_sync, grid_sync, grid_total, load_coherent, warp_sum_add
from warpfem.kernels.product import (
    OwnChunk,
    chunk_gather,
    gather_terms,
    held_terms,
    live_pairs,
    load_chunk,
    own_chunk_product,
    pair_share,
)


@wp.struct
class RowState:
    """One row's vectors of the pipelined iteration (see the module docstring)."""

    x: wp.vec3
    r: wp.vec3
    u: wp.vec3
    w: wp.vec3
    p: wp.vec3
    s: wp.vec3
    q: wp.vec3
    z: wp.vec3


@wp.struct
class HeldPair:
    """A contact pair touching rows of the thread's block, in registers for the solve (``live`` 0: none)."""

    verts_a: wp.vec4i
    weights_a: wp.vec4
    verts_b: wp.vec4i
    weights_b: wp.vec4
    C: wp.mat33
    live: int


@wp.func
def touches(verts: wp.vec4i, lo: int, hi: int) -> bool:
    """Whether any of the four vertices is a row in [lo, hi)."""
    hit = False
    for k in range(4):
        if verts[k] >= lo and verts[k] < hi:
            hit = True
    return hit


@wp.func
def load_pair(
    c: int,
    live: int,
    lo: int,
    hi: int,
    pair_verts_a: wp.array(dtype=wp.vec4i),
    pair_weights_a: wp.array(dtype=wp.vec4),
    pair_verts_b: wp.array(dtype=wp.vec4i),
    pair_weights_b: wp.array(dtype=wp.vec4),
    pair_matrix: wp.array(dtype=wp.mat33),
) -> HeldPair:
    """Pair c if it is live and touches a row in [lo, hi), else a pair with ``live`` 0."""
    h = HeldPair()
    if c < live:
        h.verts_a = pair_verts_a[c]
        h.verts_b = pair_verts_b[c]
        h.weights_a = pair_weights_a[c]
        h.weights_b = pair_weights_b[c]
        h.C = pair_matrix[c]
        if touches(h.verts_a, lo, hi) or touches(h.verts_b, lo, hi):
            h.live = 1
    return h


@wp.func
def pair_to_block(h: HeldPair, v: wp.array(dtype=wp.vec3), offset: int, lo: int, hi: int, acc: wp.array(dtype=wp.vec3)):
    """Add the pair's share of A v (less its diagonal blocks, as ``embedded_product``) to the block's rows.

    Rows outside the block's [lo, hi) are left to the blocks that own them.
    """
    if h.live == 0:
        return
    Va = wp.matrix_from_rows(
        v[offset + h.verts_a[0]], v[offset + h.verts_a[1]], v[offset + h.verts_a[2]], v[offset + h.verts_a[3]]
    )
    Vb = wp.matrix_from_rows(
        v[offset + h.verts_b[0]], v[offset + h.verts_b[1]], v[offset + h.verts_b[2]], v[offset + h.verts_b[3]]
    )
    jv = wp.vec3()
    for k in range(4):
        jv += h.weights_a[k] * Va[k] - h.weights_b[k] * Vb[k]
    for k in range(4):
        a = h.verts_a[k]
        if a >= lo and a < hi:
            block_accumulate(acc, a - lo, h.weights_a[k] * (h.C * (jv - h.weights_a[k] * Va[k])), 0)
        b = h.verts_b[k]
        if b >= lo and b < hi:
            block_accumulate(acc, b - lo, -h.weights_b[k] * (h.C * (jv + h.weights_b[k] * Vb[k])), 0)


@wp.func
def owned_product(
    held: int,
    t: int,
    block_threads: int,
    chunk: OwnChunk,
    pair0: HeldPair,
    pair1: HeldPair,
    ch_lo: int,
    ch_hi: int,
    lo: int,
    hi: int,
    chunk_row: wp.array(dtype=wp.int32),
    chunk_start: wp.array(dtype=wp.int32),
    chunk_end: wp.array(dtype=wp.int32),
    entry_col: wp.array(dtype=wp.int32),
    entry_slot: wp.array(dtype=wp.int32),
    values: wp.array(dtype=wp.mat33),
    pair_count: wp.array(dtype=wp.int32),
    pair_verts_a: wp.array(dtype=wp.vec4i),
    pair_weights_a: wp.array(dtype=wp.vec4),
    pair_verts_b: wp.array(dtype=wp.vec4i),
    pair_weights_b: wp.array(dtype=wp.vec4),
    pair_matrix: wp.array(dtype=wp.mat33),
    v: wp.array(dtype=wp.vec3),
    offset: int,
    acc: wp.array(dtype=wp.vec3),
):
    """The calling thread's share of (A v) on its block's rows [lo, hi), added into the block accumulator.

    Held (CUDA): its chunk and two pairs from registers, pairs past ``2 block_threads`` read from memory;
    else (the CPU's one thread) every chunk ``ch_lo + t``, ``ch_lo + t + block_threads``, ... and every pair.
    Ends with :func:`block_sync`: the block's rows of A v are then complete in the accumulator.
    """
    first_unheld = t
    if held != 0:
        if chunk.count > 0:
            block_accumulate(acc, chunk.row - lo, held_terms(chunk, v, offset), 0)
        pair_to_block(pair0, v, offset, lo, hi, acc)
        pair_to_block(pair1, v, offset, lo, hi, acc)
        first_unheld = t + 2 * block_threads
    else:
        for i in range(ch_lo + t, ch_hi, block_threads):
            terms = gather_terms(i, chunk_start, chunk_end, entry_col, entry_slot, values, v, offset)
            block_accumulate(acc, chunk_row[i] - lo, terms, 0)
    live = live_pairs(pair_count, pair_matrix)
    for c in range(first_unheld, live, block_threads):
        h = load_pair(c, live, lo, hi, pair_verts_a, pair_weights_a, pair_verts_b, pair_weights_b, pair_matrix)
        pair_to_block(h, v, offset, lo, hi, acc)
    block_sync()


@wp.func
def advance_row(st: RowState, m: wp.vec3, n: wp.vec3, a: float, beta: float) -> RowState:
    """One pipelined iteration of a row: the recurrences of the module docstring, from m = M^-1 w and n = A m."""
    out = RowState()
    out.z = n + beta * st.z
    out.q = m + beta * st.q
    out.s = st.w + beta * st.s
    out.p = st.u + beta * st.p
    out.x = st.x + a * out.p
    out.r = st.r - a * out.s
    out.u = st.u - a * out.q
    out.w = st.w - a * out.z
    return out


@wp.func
def load_row(
    i: int,
    x: wp.array(dtype=wp.vec3),
    r: wp.array(dtype=wp.vec3),
    u: wp.array(dtype=wp.vec3),
    w: wp.array(dtype=wp.vec3),
    p: wp.array(dtype=wp.vec3),
    s: wp.array(dtype=wp.vec3),
    q: wp.array(dtype=wp.vec3),
    z: wp.array(dtype=wp.vec3),
) -> RowState:
    """Row i's vectors from the arrays."""
    st = RowState()
    st.x = x[i]
    st.r = r[i]
    st.u = u[i]
    st.w = w[i]
    st.p = p[i]
    st.s = s[i]
    st.q = q[i]
    st.z = z[i]
    return st


@wp.func
def store_row(
    i: int,
    st: RowState,
    x: wp.array(dtype=wp.vec3),
    r: wp.array(dtype=wp.vec3),
    u: wp.array(dtype=wp.vec3),
    w: wp.array(dtype=wp.vec3),
    p: wp.array(dtype=wp.vec3),
    s: wp.array(dtype=wp.vec3),
    q: wp.array(dtype=wp.vec3),
    z: wp.array(dtype=wp.vec3),
):
    """Row i's vectors into the arrays."""
    x[i] = st.x
    r[i] = st.r
    u[i] = st.u
    w[i] = st.w
    p[i] = st.p
    s[i] = st.s
    q[i] = st.q
    z[i] = st.z


@wp.func
def row_dots(st: RowState) -> wp.vec2:
    """Row's share of (gamma, delta) = (r.u, w.u)."""
    return wp.vec2(wp.dot(st.r, st.u), wp.dot(st.w, st.u))


@wp.kernel
def cg_solve_pipelined(
    # inputs: launch shape
    threads: int,
    blocks: int,
    block_threads: int,
    held: int,
    replace_every: int,
    # inputs: block layout (block k owns rows block_row[k]..block_row[k+1] and their chunks)
    block_row: wp.array(dtype=wp.int32),
    block_chunk: wp.array(dtype=wp.int32),
    # inputs: matrix (gathered chunks)
    chunk_row: wp.array(dtype=wp.int32),
    chunk_start: wp.array(dtype=wp.int32),
    chunk_end: wp.array(dtype=wp.int32),
    entry_col: wp.array(dtype=wp.int32),
    entry_slot: wp.array(dtype=wp.int32),
    values: wp.array(dtype=wp.mat33),
    pair_count: wp.array(dtype=wp.int32),
    pair_verts_a: wp.array(dtype=wp.vec4i),
    pair_weights_a: wp.array(dtype=wp.vec4),
    pair_verts_b: wp.array(dtype=wp.vec4i),
    pair_weights_b: wp.array(dtype=wp.vec4),
    pair_matrix: wp.array(dtype=wp.mat33),
    # inputs: system and limits
    diag_inv: wp.array(dtype=wp.mat33),
    free: wp.array(dtype=wp.int32),
    b: wp.array(dtype=wp.vec3),
    direction: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    tolerance: wp.array(dtype=float),
    max_iterations: wp.array(dtype=wp.int32),
    # synchronisation (zeroed by cg_solve_reset, as are w and s)
    barrier: wp.array(dtype=wp.int32),
    totals: wp.array(dtype=float),
    # scratch: the CPU's accumulator (n rows), m twice (2 n rows), q and z (n rows each)
    acc: wp.array(dtype=wp.vec3),
    m_buf: wp.array(dtype=wp.vec3),
    q_buf: wp.array(dtype=wp.vec3),
    z_buf: wp.array(dtype=wp.vec3),
    # outputs
    x_out: wp.array(dtype=wp.vec3),
    r_out: wp.array(dtype=wp.vec3),
    u_out: wp.array(dtype=wp.vec3),
    p_out: wp.array(dtype=wp.vec3),
    s_out: wp.array(dtype=wp.vec3),
    w_out: wp.array(dtype=wp.vec3),
    counts_out: wp.array(dtype=wp.int32),
    residual_max_out: wp.array(dtype=float),
    stalled_out: wp.array(dtype=wp.int32),
):
    """The whole pipelined solve in one persistent launch of ``blocks`` blocks of ``block_threads`` threads.

    ``held`` (CUDA, every block with at most ``block_threads`` rows and chunks): thread t of block k holds
    chunk ``block_chunk[k] + t``, pairs t and t + block_threads if they touch the block, and row
    ``block_row[k] + t``'s vectors; else one thread walks every row and chunk. Counts the solve like
    ``cg_solve``.
    """
    lane = wp.tid()
    n = free.shape[0]
    blk = lane // block_threads
    t = lane - blk * block_threads
    lo = block_row[blk]
    hi = block_row[blk + 1]
    ch_lo = block_chunk[blk]
    ch_hi = block_chunk[blk + 1]
    n_chunks = chunk_row.shape[0]
    chunk = OwnChunk()
    pair0 = HeldPair()
    pair1 = HeldPair()
    if held != 0:
        if ch_lo + t < ch_hi:
            chunk = load_chunk(ch_lo + t, True, chunk_row, chunk_start, chunk_end, entry_col, entry_slot, values)
        live = live_pairs(pair_count, pair_matrix)
        pair0 = load_pair(t, live, lo, hi, pair_verts_a, pair_weights_a, pair_verts_b, pair_weights_b, pair_matrix)
        pair1 = load_pair(
            t + block_threads, live, lo, hi, pair_verts_a, pair_weights_a, pair_verts_b, pair_weights_b, pair_matrix
        )
    for i in range(lo + t, hi, block_threads):  # zero the accumulator (shared memory starts undefined), q, z
        block_accumulate(acc, i - lo, wp.vec3(), 1)
        q_buf[i] = wp.vec3()
        z_buf[i] = wp.vec3()

    # the start, as cg_solve's: A x into w and A d into s (atomic adds), the step along d, r, u
    for v in range(2):
        if held != 0:
            if chunk.count > 0:
                if v == 0:
                    own_chunk_product(chunk, x_out, w_out)
                else:
                    own_chunk_product(chunk, direction, s_out)
        else:
            for i in range(lane, n_chunks, threads):
                if v == 0:
                    chunk_gather(i, chunk_row, chunk_start, chunk_end, entry_col, entry_slot, values, x_out, w_out)
                else:
                    chunk_gather(i, chunk_row, chunk_start, chunk_end, entry_col, entry_slot, values, direction, s_out)
    pair_share(
        lane,
        threads,
        n_chunks,
        pair_count,
        pair_verts_a,
        pair_weights_a,
        pair_verts_b,
        pair_weights_b,
        pair_matrix,
        x_out,
        w_out,
    )
    pair_share(
        lane,
        threads,
        n_chunks,
        pair_count,
        pair_verts_a,
        pair_weights_a,
        pair_verts_b,
        pair_weights_b,
        pair_matrix,
        direction,
        s_out,
    )
    sync = blocks
    grid_sync(barrier, sync, stalled_out)
    proj = wp.vec3()
    for i in range(lane, n, threads):
        proj += project_row(i, free, b, direction, mass, w_out, s_out)
    warp_sum_add(proj[0], totals, 2)
    warp_sum_add(proj[1], totals, 3)
    sync += blocks
    dmd = grid_total(proj[2], totals, 4, barrier, sync, stalled_out)
    theta = line_step(load_coherent(totals, 2), load_coherent(totals, 3), dmd)
    dots = wp.vec2()
    for i in range(lane, n, threads):
        dots += init_row(i, theta, diag_inv, free, b, direction, x_out, w_out, r_out, u_out, p_out, s_out)
    warp_sum_add(dots[1], totals, 1)
    sync += blocks
    gamma = grid_total(dots[0], totals, 0, barrier, sync, stalled_out)
    bz = load_coherent(totals, 1)
    tol2 = tolerance[0] * tolerance[0]
    max_k = max_iterations[0]

    # w = A u (u published by the last barrier); each row's vectors into registers (CUDA) or the arrays
    mine = RowState()
    k = int(0)
    refresh = bool(True)
    gamma_prev = float(0.0)
    a_prev = float(0.0)
    while True:
        if refresh:  # the start, and after a replacement: w = A u from the published u, the rest from the arrays
            owned_product(
                held,
                t,
                block_threads,
                chunk,
                pair0,
                pair1,
                ch_lo,
                ch_hi,
                lo,
                hi,
                chunk_row,
                chunk_start,
                chunk_end,
                entry_col,
                entry_slot,
                values,
                pair_count,
                pair_verts_a,
                pair_weights_a,
                pair_verts_b,
                pair_weights_b,
                pair_matrix,
                u_out,
                0,
                acc,
            )
            for i in range(lo + t, hi, block_threads):
                w_i = block_accumulate(acc, i - lo, wp.vec3(), 1)
                w_out[i] = wp.where(free[i] != 0, w_i, wp.vec3())
                if held != 0:
                    mine = load_row(i, x_out, r_out, u_out, w_out, p_out, s_out, q_buf, z_buf)
            refresh = False
        # gamma = r.u, delta = w.u and m = M^-1 w published at one barrier
        parity = (k % 2) * n
        gd = wp.vec2()
        if held != 0:
            if lo + t < hi:
                gd = row_dots(mine)
                m_buf[parity + lo + t] = diag_inv[lo + t] * mine.w
        else:
            for i in range(lo + t, hi, block_threads):
                st = load_row(i, x_out, r_out, u_out, w_out, p_out, s_out, q_buf, z_buf)
                gd += row_dots(st)
                m_buf[parity + i] = diag_inv[i] * st.w
        warp_sum_add(gd[1], totals, 6 + 2 * k)
        sync += blocks
        gamma = grid_total(gd[0], totals, 5 + 2 * k, barrier, sync, stalled_out)
        delta = load_coherent(totals, 6 + 2 * k)
        if k >= max_k or gamma <= 0.0 or gamma <= tol2 * bz:
            break
        a, beta = step_sizes(k, gamma, gamma_prev, delta, a_prev)
        if a <= 0.0:
            break
        # n = A m on the block's rows, then every vector of the row by its recurrence
        owned_product(
            held,
            t,
            block_threads,
            chunk,
            pair0,
            pair1,
            ch_lo,
            ch_hi,
            lo,
            hi,
            chunk_row,
            chunk_start,
            chunk_end,
            entry_col,
            entry_slot,
            values,
            pair_count,
            pair_verts_a,
            pair_weights_a,
            pair_verts_b,
            pair_weights_b,
            pair_matrix,
            m_buf,
            parity,
            acc,
        )
        for i in range(lo + t, hi, block_threads):
            n_i = wp.where(free[i] != 0, block_accumulate(acc, i - lo, wp.vec3(), 1), wp.vec3())
            m_i = m_buf[parity + i]
            if held != 0:
                mine = advance_row(mine, m_i, n_i, a, beta)
            else:
                st = advance_row(load_row(i, x_out, r_out, u_out, w_out, p_out, s_out, q_buf, z_buf), m_i, n_i, a, beta)
                store_row(i, st, x_out, r_out, u_out, w_out, p_out, s_out, q_buf, z_buf)
        gamma_prev = gamma
        a_prev = a
        k += 1
        if replace_every > 0 and k % replace_every == 0:
            # r = b - A x and u = M^-1 r afresh (x published at a barrier), then w = A u at the loop's top
            if held != 0:
                for i in range(lo + t, hi, block_threads):
                    store_row(i, mine, x_out, r_out, u_out, w_out, p_out, s_out, q_buf, z_buf)
            sync += blocks
            grid_sync(barrier, sync, stalled_out)
            owned_product(
                held,
                t,
                block_threads,
                chunk,
                pair0,
                pair1,
                ch_lo,
                ch_hi,
                lo,
                hi,
                chunk_row,
                chunk_start,
                chunk_end,
                entry_col,
                entry_slot,
                values,
                pair_count,
                pair_verts_a,
                pair_weights_a,
                pair_verts_b,
                pair_weights_b,
                pair_matrix,
                x_out,
                0,
                acc,
            )
            for i in range(lo + t, hi, block_threads):
                ax = block_accumulate(acc, i - lo, wp.vec3(), 1)
                r_i = wp.where(free[i] != 0, b[i] - ax, wp.vec3())
                r_out[i] = r_i
                u_out[i] = diag_inv[i] * r_i
            sync += blocks
            grid_sync(barrier, sync, stalled_out)
            refresh = True
    if held != 0:
        for i in range(lo + t, hi, block_threads):
            x_out[i] = mine.x
    if lane == 0:
        counts_out[0] = counts_out[0] + 1
        counts_out[1] = counts_out[1] + k
        res = float(0.0)
        if bz > 0.0:
            res = wp.sqrt(wp.max(gamma, 0.0) / bz)
        residual_max_out[0] = wp.max(residual_max_out[0], res)

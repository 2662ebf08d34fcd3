"""Block-Jacobi preconditioned conjugate gradients on a 3x3-block CSR matrix, as fused kernels.

The iteration is Chronopoulos and Gear's single-reduction form of PCG: each iteration is two launches,
``cg_update`` (p, s = A p, x, r, u = M^-1 r and the dot r.u) and ``cg_apply`` (w = A u and the dot u.w),
against four launches and two reductions of the textbook form. The scalars follow from the two dots:
``beta_k = gamma_k / gamma_{k-1}``, ``alpha_k = gamma_k / (delta_k - beta_k gamma_k / alpha_{k-1})``.

``cg_apply`` runs one thread per chunk of at most a few nonzero blocks of a row (more threads and shorter
dependent loops than a thread per row: small systems are latency bound, large ones read the blocks in
nearly coalesced runs) and adds into a zeroed output with atomics; a coupling term (pairs of points
embedded in the mesh, such as contacts) is applied by extra threads of the same launch. Dot products are
reduced per block (a tile sum, then one atomic add per block). All per-iteration scalars live in device
arrays indexed by the device-side iteration counter plus the unrolled step, so the loop needs no host
synchronisation and can be captured with ``wp.capture_while``; an iteration past convergence or past the
cap changes nothing. Rows with ``free == 0`` (pinned vertices) are held at their initial value.
"""

import warp as wp


@wp.func
def block_sum(value: float, total_out: wp.array(dtype=float), index: int):
    """Add ``value`` of every thread of the block into ``total_out[index]``: one atomic per block.

    A cooperative tile reduction (every thread of the block must reach it); on the CPU a block is one
    thread, so it is a plain atomic add.
    """
    wp.tile_atomic_add(total_out, wp.tile_sum(wp.tile(value)), offset=index)


@wp.func
def is_active(
    k: int, gamma: wp.array(dtype=float), bz: wp.array(dtype=float), tolerance: float, max_iterations: int
) -> bool:
    """Whether iteration ``k`` runs: under the cap, residual r.M^-1 r above tolerance^2 b.M^-1 b, no breakdown."""
    g = gamma[k]
    return k < max_iterations and g > 0.0 and g > tolerance * tolerance * bz[0]


@wp.func
def embedded_product(
    verts_a: wp.vec4i,
    weights_a: wp.vec4,
    verts_b: wp.vec4i,
    weights_b: wp.vec4,
    C: wp.mat33,
    u: wp.array(dtype=wp.vec3),
    w_out: wp.array(dtype=wp.vec3),
) -> float:
    """w += (J^T C J less its diagonal blocks) u for one pair; returns this pair's share of u.w.

    ``J u = sum_k weights_a[k] u[verts_a[k]] - weights_b[k] u[verts_b[k]]`` is the pair's relative value.
    """
    s = wp.vec3()
    for k in range(4):
        s += weights_a[k] * u[verts_a[k]] - weights_b[k] * u[verts_b[k]]
    dot = float(0.0)
    for k in range(4):
        va = verts_a[k]
        vb = verts_b[k]
        da = weights_a[k] * (C * (s - weights_a[k] * u[va]))
        db = -weights_b[k] * (C * (s + weights_b[k] * u[vb]))
        wp.atomic_add(w_out, va, da)
        wp.atomic_add(w_out, vb, db)
        dot += wp.dot(u[va], da) + wp.dot(u[vb], db)
    return dot


@wp.kernel
def cg_apply(
    # inputs: matrix
    n_threads: int,
    chunk_row: wp.array(dtype=wp.int32),
    chunk_start: wp.array(dtype=wp.int32),
    chunk_size: int,
    row_start: wp.array(dtype=wp.int32),
    cols: wp.array(dtype=wp.int32),
    values: wp.array(dtype=wp.mat33),
    # inputs: coupling pairs (threads past the chunks)
    pair_count: wp.array(dtype=wp.int32),
    pair_verts_a: wp.array(dtype=wp.vec4i),
    pair_weights_a: wp.array(dtype=wp.vec4),
    pair_verts_b: wp.array(dtype=wp.vec4i),
    pair_weights_b: wp.array(dtype=wp.vec4),
    pair_matrix: wp.array(dtype=wp.mat33),
    # inputs: vector and iteration
    u: wp.array(dtype=wp.vec3),
    gate: int,
    iteration: wp.array(dtype=wp.int32),
    step: int,
    gamma: wp.array(dtype=float),
    bz: wp.array(dtype=float),
    tolerance: wp.array(dtype=float),
    max_iterations: wp.array(dtype=wp.int32),
    # outputs
    w_out: wp.array(dtype=wp.vec3),
    delta_out: wp.array(dtype=float),
):
    """w += A u (w zeroed before); u.w into delta[k] with k = iteration + step.

    ``values`` holds the upper triangle: a block (row, c) with c > row adds A u_c to the row and A^T u_row to
    row c. u is zero on pinned rows, so they add nothing; what lands in w on them is ignored by
    ``cg_update``. With ``gate`` set, skipped (adding nothing) when iteration k will not run.
    """
    i = wp.tid()
    k = iteration[0] + step
    dot = float(0.0)
    run = True
    if gate != 0:
        run = is_active(k, gamma, bz, tolerance[0], max_iterations[0])
    if i < n_threads and run:
        n_chunks = chunk_row.shape[0]
        if i < n_chunks:
            row = chunk_row[i]
            u_row = u[row]
            acc = wp.vec3()
            own = wp.vec3()
            for j in range(chunk_start[i], wp.min(chunk_start[i] + chunk_size, row_start[row + 1])):
                c = cols[j]
                A = values[j]
                if c != row:
                    acc += A * u[c]
                    wp.atomic_add(w_out, c, wp.transpose(A) * u_row)
                else:
                    own = A * u_row
            wp.atomic_add(w_out, row, acc + own)
            # u.(A u) over this chunk's blocks and the transposes of its off-diagonal ones
            dot = wp.dot(u_row, 2.0 * acc + own)
        else:
            c = i - n_chunks
            if c < wp.min(pair_count[0], pair_matrix.shape[0]):
                dot = embedded_product(
                    pair_verts_a[c],
                    pair_weights_a[c],
                    pair_verts_b[c],
                    pair_weights_b[c],
                    pair_matrix[c],
                    u,
                    w_out,
                )
    block_sum(dot, delta_out, k)


@wp.kernel
def cg_reset(
    n: int,
    w_out: wp.array(dtype=wp.vec3),
    gamma_out: wp.array(dtype=float),
    delta_out: wp.array(dtype=float),
    bz_out: wp.array(dtype=float),
    scratch_out: wp.array(dtype=float),
    iteration_out: wp.array(dtype=wp.int32),
    done_out: wp.array(dtype=wp.int32),
):
    """Zero w (n rows), the per-iteration dots and the scalars and counters of a solve."""
    i = wp.tid()
    if i < n:
        w_out[i] = wp.vec3()
    if i < gamma_out.shape[0]:
        gamma_out[i] = 0.0
        delta_out[i] = 0.0
    if i == 0:
        bz_out[0] = 0.0
        scratch_out[0] = 0.0
        iteration_out[0] = 0
        done_out[0] = 0


@wp.kernel
def cg_init(
    # inputs
    n: int,
    diag_inv: wp.array(dtype=wp.mat33),
    free: wp.array(dtype=wp.int32),
    b: wp.array(dtype=wp.vec3),
    # outputs (w holds A x on entry)
    w_out: wp.array(dtype=wp.vec3),
    r_out: wp.array(dtype=wp.vec3),
    u_out: wp.array(dtype=wp.vec3),
    p_out: wp.array(dtype=wp.vec3),
    s_out: wp.array(dtype=wp.vec3),
    gamma_out: wp.array(dtype=float),
    bz_out: wp.array(dtype=float),
):
    """r = b - A x (given in w), u = M^-1 r, p = s = w = 0; r.u into gamma[0], b.M^-1 b into bz[0]."""
    i = wp.tid()
    ru = float(0.0)
    bz = float(0.0)
    if i < n:
        r = wp.vec3()
        u = wp.vec3()
        if free[i] != 0:
            r = b[i] - w_out[i]
            u = diag_inv[i] * r
            ru = wp.dot(r, u)
            bz = wp.dot(b[i], diag_inv[i] * b[i])
        r_out[i] = r
        u_out[i] = u
        p_out[i] = wp.vec3()
        s_out[i] = wp.vec3()
        w_out[i] = wp.vec3()
    block_sum(ru, gamma_out, 0)
    block_sum(bz, bz_out, 0)


@wp.func
def step_sizes(k: int, gamma: wp.array(dtype=float), delta: wp.array(dtype=float), alpha: wp.array(dtype=float)):
    """(alpha_k, beta_k) of Chronopoulos-Gear PCG; alpha_k = 0 on breakdown (a non-positive curvature)."""
    beta = float(0.0)
    denom = delta[k]
    if k > 0:
        beta = gamma[k] / gamma[k - 1]
        if alpha[k - 1] > 0.0:
            denom = denom - beta * gamma[k] / alpha[k - 1]
        else:
            denom = 0.0
    a = float(0.0)
    if denom > 0.0:
        a = gamma[k] / denom
    return a, beta


@wp.kernel
def cg_update(
    # inputs
    n: int,
    diag_inv: wp.array(dtype=wp.mat33),
    iteration: wp.array(dtype=wp.int32),
    step: int,
    gamma: wp.array(dtype=float),
    delta: wp.array(dtype=float),
    bz: wp.array(dtype=float),
    tolerance: wp.array(dtype=float),
    max_iterations: wp.array(dtype=wp.int32),
    free: wp.array(dtype=wp.int32),
    # outputs
    alpha_out: wp.array(dtype=float),
    done_out: wp.array(dtype=wp.int32),
    x_out: wp.array(dtype=wp.vec3),
    r_out: wp.array(dtype=wp.vec3),
    u_out: wp.array(dtype=wp.vec3),
    p_out: wp.array(dtype=wp.vec3),
    s_out: wp.array(dtype=wp.vec3),
    w_out: wp.array(dtype=wp.vec3),
    gamma_out: wp.array(dtype=float),
):
    """One iteration, k = iteration + step (nothing if k does not run).

    p = u + beta p, s = w + beta s (= A p), x += alpha p, r -= alpha s, u = M^-1 r, w = 0 on free rows
    (pinned rows keep x and zero r, u, p, s); r.u into gamma[k+1]. Thread 0 records alpha[k] and the
    iterations done.
    """
    i = wp.tid()
    k = iteration[0] + step
    ru = float(0.0)
    if is_active(k, gamma, bz, tolerance[0], max_iterations[0]):
        a, beta = step_sizes(k, gamma, delta, alpha_out)
        if i == 0:
            alpha_out[k] = a
            done_out[0] = wp.where(a > 0.0, k + 1, k)
        if i < n and a > 0.0 and free[i] == 0:
            w_out[i] = wp.vec3()
        if i < n and a > 0.0 and free[i] != 0:
            p = u_out[i] + beta * p_out[i]
            s = w_out[i] + beta * s_out[i]
            x_out[i] = x_out[i] + a * p
            r = r_out[i] - a * s
            u = diag_inv[i] * r
            p_out[i] = p
            s_out[i] = s
            r_out[i] = r
            u_out[i] = u
            w_out[i] = wp.vec3()
            ru = wp.dot(r, u)
    block_sum(ru, gamma_out, k + 1)


@wp.kernel
def cg_start(
    gamma: wp.array(dtype=float),
    bz: wp.array(dtype=float),
    tolerance: wp.array(dtype=float),
    max_iterations: wp.array(dtype=wp.int32),
    cond_out: wp.array(dtype=wp.int32),
):
    """Single thread: whether to iterate at all."""
    cond_out[0] = wp.where(is_active(0, gamma, bz, tolerance[0], max_iterations[0]), 1, 0)


@wp.kernel
def cg_advance(
    unroll: int,
    gamma: wp.array(dtype=float),
    bz: wp.array(dtype=float),
    tolerance: wp.array(dtype=float),
    max_iterations: wp.array(dtype=wp.int32),
    iteration_out: wp.array(dtype=wp.int32),
    cond_out: wp.array(dtype=wp.int32),
):
    """Single thread: iteration += unroll; keep going while the next iteration runs."""
    k = iteration_out[0] + unroll
    iteration_out[0] = k
    cond_out[0] = wp.where(is_active(k, gamma, bz, tolerance[0], max_iterations[0]), 1, 0)


@wp.kernel
def cg_finish(
    gamma: wp.array(dtype=float),
    bz: wp.array(dtype=float),
    done: wp.array(dtype=wp.int32),
    counts_out: wp.array(dtype=wp.int32),
    residual_max_out: wp.array(dtype=float),
):
    """Single thread: counts the solve and its iterations (counts[0], counts[1]); keeps the largest residual."""
    k = done[0]
    counts_out[0] = counts_out[0] + 1
    counts_out[1] = counts_out[1] + k
    res = float(0.0)
    if bz[0] > 0.0:
        res = wp.sqrt(wp.max(gamma[k], 0.0) / bz[0])
    residual_max_out[0] = wp.max(residual_max_out[0], res)

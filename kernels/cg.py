"""Block-Jacobi preconditioned conjugate gradients on a 3x3-block CSR matrix, as fused kernels.

The iteration is Chronopoulos and Gear's single-reduction form of PCG (one reduction of two dots per iteration:
``beta_k = gamma_k / gamma_{k-1}``, ``alpha_k = gamma_k / (delta_k - beta_k gamma_k / alpha_{k-1})``), run either
as two launches per iteration (``cg_update``: p, s = A p, x, r, u = M^-1 r and r.u; ``cg_apply``: w = A u and
u.w) under ``wp.capture_while``, with per-iteration scalars in device arrays and no host synchronisation, or as
one persistent launch whose blocks meet at grid-wide barriers (:func:`grid_total`), the default
(``warpfem.sim.cg.DEFAULT_MODE``; one thread on the CPU). The product (chunks of a few blocks of a row, gathered
or scattered, and the coupling pairs of contacts) is in :mod:`warpfem.kernels.product`. Rows with ``free == 0``
(pinned vertices) keep their initial value.

The start is x + theta d, the given x moved along a direction d (the last step's velocity change) by the step
that minimises the A-norm error along d, clamped to [0, 1] and taken only along a smooth direction
(:func:`line_step`): never a worse start than x.

The persistent solve comes in three forms by size: ``cg_solve_held`` (and ``cg_solve_held_wide`` in wider
blocks) where every chunk has a thread, which keeps it in registers and meets at one barrier an iteration;
``cg_solve_shared`` where each thread's few chunks fit the block's shared memory; else ``cg_solve``, which reads
the matrix every iteration.
"""

import warp as wp

from .grid import grid_total, load_coherent, warp_sum_add
from .product import (
    PAIR_LANES,
    SHARED_BLOCK,
    SHARED_ROWS,
    BlockMatrix,
    OwnChunk,
    Pairs,
    advanced,
    advanced_u,
    chunk_product,
    held_corner_phase,
    held_terms,
    hold_chunks,
    hold_pair,
    live_pairs,
    own_chunk,
    pair_corner,
    pair_product,
    partial_product,
    shared_product,
)

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated


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


@wp.kernel
def cg_apply(
    # inputs: matrix
    n_threads: int,
    matrix: BlockMatrix,
    # inputs: coupling pairs (threads past the chunks)
    pairs: Pairs,
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

    The chunks gather or scatter (see ``chunk_product``). u is zero on pinned rows, so they add nothing; what
    lands in w on them is ignored by ``cg_update``. Threads past the chunks apply the coupling pairs. With
    ``gate`` set, skipped (adding nothing) when iteration k will not run.
    """
    i = wp.tid()
    k = iteration[0] + step
    dot = float(0.0)
    run = True
    if gate != 0:
        run = is_active(k, gamma, bz, tolerance[0], max_iterations[0])
    if i < n_threads and run:
        n_chunks = matrix.chunk_row.shape[0]
        if i < n_chunks:
            dot = chunk_product(i, matrix, u, w_out)
        else:  # the pair threads stride over the live pairs (usually far fewer than the capacity)
            for c in range(i - n_chunks, live_pairs(pairs), n_threads - n_chunks):
                dot += pair_product(c, pairs, u, w_out)
    block_sum(dot, delta_out, k)


@wp.kernel
def cg_reset(
    n: int,
    w_out: wp.array(dtype=wp.vec3),
    s_out: wp.array(dtype=wp.vec3),
    gamma_out: wp.array(dtype=float),
    delta_out: wp.array(dtype=float),
    bz_out: wp.array(dtype=float),
    scratch_out: wp.array(dtype=float),
    project_out: wp.array(dtype=float),
    iteration_out: wp.array(dtype=wp.int32),
    done_out: wp.array(dtype=wp.int32),
):
    """Zero w and s (n rows), the per-iteration dots and the scalars and counters of a solve."""
    i = wp.tid()
    if i < n:
        w_out[i] = wp.vec3()
        s_out[i] = wp.vec3()
    if i < gamma_out.shape[0]:
        gamma_out[i] = 0.0
        delta_out[i] = 0.0
    if i == 0:
        bz_out[0] = 0.0
        scratch_out[0] = 0.0
        project_out[0] = 0.0
        project_out[1] = 0.0
        project_out[2] = 0.0
        iteration_out[0] = 0
        done_out[0] = 0


@wp.kernel
def cg_project(
    n: int,
    free: wp.array(dtype=wp.int32),
    b: wp.array(dtype=wp.vec3),
    direction: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    w: wp.array(dtype=wp.vec3),
    s: wp.array(dtype=wp.vec3),
    project_out: wp.array(dtype=float),
):
    """d.(b - A x), d.A d and d.M d into project[0:3] (A x in w, A d in s)."""
    i = wp.tid()
    dots = wp.vec3()
    if i < n:
        dots = project_row(i, free, b, direction, mass, w, s)
    block_sum(dots[0], project_out, 0)
    block_sum(dots[1], project_out, 1)
    block_sum(dots[2], project_out, 2)


@wp.func
def project_row(
    i: int,
    free: wp.array(dtype=wp.int32),
    b: wp.array(dtype=wp.vec3),
    direction: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    w: wp.array(dtype=wp.vec3),
    s: wp.array(dtype=wp.vec3),
) -> wp.vec3:
    """Row i's share of (d.(b - A x), d.A d, d.M d), with A x in w and A d in s (d: the start's direction)."""
    d = direction[i]
    b_i, w_i, s_i, m = b[i], w[i], s[i], mass[i]
    if free[i] == 0:
        return wp.vec3()
    return wp.vec3(wp.dot(d, b_i - w_i), wp.dot(d, s_i), m * wp.dot(d, d))


CAP_SLACK = 1.01
"""A final residual this much above the tolerance (float32 rounding aside) means CG stopped at its cap."""

SMOOTH = 2.0
"""The largest d.A d / d.M d of a direction the start moves along: a smooth motion (a fall, a push: kinetic
energy, little strain) has about 1; a direction in the stiff modes (the last step's oscillation or rounding
at float32's limit) is not extrapolated, since moving along it feeds energy into a stiff body at large steps."""


@wp.func
def line_step(dr: float, dad: float, dmd: float) -> float:
    """The step along d minimising the A-norm error of x + theta d, in [0, 1]; 0 unless 0 < d.A d <= SMOOTH d.M d."""
    theta = float(0.0)
    if dad > 0.0 and dad <= SMOOTH * dmd:
        theta = wp.clamp(dr / dad, 0.0, 1.0)
    return theta


@wp.func
def init_row(
    i: int,
    theta: float,
    diag_inv: wp.array(dtype=wp.mat33),
    free: wp.array(dtype=wp.int32),
    b: wp.array(dtype=wp.vec3),
    direction: wp.array(dtype=wp.vec3),
    x_out: wp.array(dtype=wp.vec3),
    w_out: wp.array(dtype=wp.vec3),
    r_out: wp.array(dtype=wp.vec3),
    u_out: wp.array(dtype=wp.vec3),
    p_out: wp.array(dtype=wp.vec3),
    s_out: wp.array(dtype=wp.vec3),
) -> wp.vec2:
    """Row i of the start: x += theta d, r = b - A x (A x in w, A d in s), u = M^-1 r, p = s = w = 0.

    Returns (r.u, b.M^-1 b).
    """
    r = wp.vec3()
    u = wp.vec3()
    bz = float(0.0)
    if free[i] != 0:
        x_out[i] = x_out[i] + theta * direction[i]
        r = b[i] - w_out[i] - theta * s_out[i]
        u = diag_inv[i] * r
        bz = wp.dot(b[i], diag_inv[i] * b[i])
    r_out[i] = r
    u_out[i] = u
    p_out[i] = wp.vec3()
    s_out[i] = wp.vec3()
    w_out[i] = wp.vec3()
    return wp.vec2(wp.dot(r, u), bz)


@wp.func
def update_row(
    i: int,
    a: float,
    beta: float,
    diag_inv: wp.array(dtype=wp.mat33),
    free: wp.array(dtype=wp.int32),
    x_out: wp.array(dtype=wp.vec3),
    r_out: wp.array(dtype=wp.vec3),
    u_out: wp.array(dtype=wp.vec3),
    p_out: wp.array(dtype=wp.vec3),
    s_out: wp.array(dtype=wp.vec3),
    w_out: wp.array(dtype=wp.vec3),
) -> float:
    """Row i of an iteration: p = u + beta p, s = w + beta s, x += a p, r -= a s, u = M^-1 r, w = 0; returns r.u.

    Pinned rows only get w = 0 (their x stays, their r, u, p, s stay zero). Every load is issued before the
    pin test, so the row costs one round trip to memory, not two.
    """
    pinned = free[i] == 0
    u_i, p_i, w_i, s_i, x_i, r_i, D = u_out[i], p_out[i], w_out[i], s_out[i], x_out[i], r_out[i], diag_inv[i]
    if pinned:
        w_out[i] = wp.vec3()
        return 0.0
    p = u_i + beta * p_i
    s = w_i + beta * s_i
    x_out[i] = x_i + a * p
    r = r_i - a * s
    u = D * r
    p_out[i] = p
    s_out[i] = s
    r_out[i] = r
    u_out[i] = u
    w_out[i] = wp.vec3()
    return wp.dot(r, u)


@wp.kernel
def cg_init(
    # inputs
    n: int,
    diag_inv: wp.array(dtype=wp.mat33),
    free: wp.array(dtype=wp.int32),
    b: wp.array(dtype=wp.vec3),
    direction: wp.array(dtype=wp.vec3),
    project: wp.array(dtype=float),
    # outputs (w holds A x and s holds A d on entry)
    x_out: wp.array(dtype=wp.vec3),
    w_out: wp.array(dtype=wp.vec3),
    r_out: wp.array(dtype=wp.vec3),
    u_out: wp.array(dtype=wp.vec3),
    p_out: wp.array(dtype=wp.vec3),
    s_out: wp.array(dtype=wp.vec3),
    gamma_out: wp.array(dtype=float),
    bz_out: wp.array(dtype=float),
):
    """x += theta d, r = b - A x, u = M^-1 r, p = s = w = 0; r.u into gamma[0], b.M^-1 b into bz[0]."""
    i = wp.tid()
    theta = line_step(project[0], project[1], project[2])
    dots = wp.vec2()
    if i < n:
        dots = init_row(i, theta, diag_inv, free, b, direction, x_out, w_out, r_out, u_out, p_out, s_out)
    block_sum(dots[0], gamma_out, 0)
    block_sum(dots[1], bz_out, 0)


@wp.func
def step_sizes(k: int, gamma: float, gamma_prev: float, delta: float, alpha_prev: float):
    """(alpha_k, beta_k) of Chronopoulos-Gear PCG from gamma_k, gamma_{k-1}, delta_k and alpha_{k-1}.

    Where rounding drives the recurrence's curvature p.A p = delta - beta gamma / alpha_{k-1} to zero or
    below (float32 on an ill-conditioned system), the iteration restarts along the preconditioned residual
    (beta = 0, curvature u.A u = delta) instead of stopping short. alpha_k = 0 only when that is not positive
    either (A not positive definite).
    """
    beta = float(0.0)
    denom = delta
    if k > 0 and alpha_prev > 0.0:
        beta = gamma / gamma_prev
        denom = delta - beta * gamma / alpha_prev
        if denom <= 1.0e-6 * delta:  # restart
            beta = 0.0
            denom = delta
    a = float(0.0)
    if denom > 0.0:
        a = gamma / denom
    return a, beta


@wp.func
def iteration_step(
    i: int,
    k: int,
    gamma: wp.array(dtype=float),
    delta: wp.array(dtype=float),
    bz: wp.array(dtype=float),
    tolerance: wp.array(dtype=float),
    max_iterations: wp.array(dtype=wp.int32),
    alpha_out: wp.array(dtype=float),
    done_out: wp.array(dtype=wp.int32),
):
    """Iteration k's (alpha, beta) of a launched solve, (0, 0) where it does not run; thread 0 records them."""
    a = float(0.0)
    beta = float(0.0)
    if is_active(k, gamma, bz, tolerance[0], max_iterations[0]):
        gamma_prev = float(0.0)
        alpha_prev = float(0.0)
        if k > 0:
            gamma_prev = gamma[k - 1]
            alpha_prev = alpha_out[k - 1]
        a, beta = step_sizes(k, gamma[k], gamma_prev, delta[k], alpha_prev)
        if i == 0:
            alpha_out[k] = a
            done_out[0] = wp.where(a > 0.0, k + 1, k)
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
    (pinned rows keep x and zero r, u, p, s); r.u into gamma[k+1]; the step sizes: :func:`iteration_step`.
    """
    i = wp.tid()
    k = iteration[0] + step
    ru = float(0.0)
    a, beta = iteration_step(i, k, gamma, delta, bz, tolerance, max_iterations, alpha_out, done_out)
    if i < n and a > 0.0:
        ru = update_row(i, a, beta, diag_inv, free, x_out, r_out, u_out, p_out, s_out, w_out)
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
    tolerance: wp.array(dtype=float),
    counts_out: wp.array(dtype=wp.int32),
    residual_max_out: wp.array(dtype=float),
):
    """Single thread: counts the solve, its iterations and whether it stopped short; keeps the largest residual."""
    k = done[0]
    record_solve(k, gamma[k], bz[0], tolerance[0], counts_out, residual_max_out)


@wp.func
def record_solve(
    k: int,
    gamma: float,
    bz: float,
    tolerance: float,
    counts_out: wp.array(dtype=wp.int32),
    residual_max_out: wp.array(dtype=float),
):
    """Count a solve of k iterations (counts[0], counts[1]); keep the largest residual sqrt(gamma / bz).

    counts[2] counts the solves whose residual ended above ``tolerance`` (0: a fixed count, never short).
    """
    counts_out[0] = counts_out[0] + 1
    counts_out[1] = counts_out[1] + k
    res = float(0.0)
    if bz > 0.0:
        res = wp.sqrt(wp.max(gamma, 0.0) / bz)
    if tolerance > 0.0 and res > CAP_SLACK * tolerance:
        counts_out[2] = counts_out[2] + 1
    residual_max_out[0] = wp.max(residual_max_out[0], res)


@wp.kernel
def cg_solve_reset(
    n: int,
    w_out: wp.array(dtype=wp.vec3),
    s_out: wp.array(dtype=wp.vec3),
    totals_out: wp.array(dtype=float),
    words_out: wp.array(dtype=wp.uint64),
):
    """Zero w and s (n rows), the side sums and the barrier words of a persistent solve."""
    i = wp.tid()
    if i < n:
        w_out[i] = wp.vec3()
        s_out[i] = wp.vec3()
    if i < totals_out.shape[0]:
        totals_out[i] = 0.0
    if i < words_out.shape[0]:
        words_out[i] = wp.uint64(0)


@wp.func
def solve_start(
    lane: int,
    threads: int,
    blocks: int,
    held: int,
    own: OwnChunk,
    matrix: BlockMatrix,
    pairs: Pairs,
    diag_inv: wp.array(dtype=wp.mat33),
    free: wp.array(dtype=wp.int32),
    b: wp.array(dtype=wp.vec3),
    direction: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    words: wp.array(dtype=wp.uint64),
    totals: wp.array(dtype=float),
    x_out: wp.array(dtype=wp.vec3),
    r_out: wp.array(dtype=wp.vec3),
    u_out: wp.array(dtype=wp.vec3),
    p_out: wp.array(dtype=wp.vec3),
    s_out: wp.array(dtype=wp.vec3),
    w_out: wp.array(dtype=wp.vec3),
    stalled_out: wp.array(dtype=wp.int32),
) -> wp.vec2:
    """A persistent solve's start (words, side sums 0-2): x moved along d, r = b - A x, u = M^-1 r; (r.u, b.M^-1 b)."""
    n = free.shape[0]
    partial_product(lane, threads, held, own, matrix, pairs, x_out, w_out)
    partial_product(lane, threads, held, own, matrix, pairs, direction, s_out)
    grid_total(0.0, words, 0, blocks, stalled_out)
    proj = wp.vec3()
    for i in range(lane, n, threads):
        proj += project_row(i, free, b, direction, mass, w_out, s_out)
    warp_sum_add(proj[0], totals, 1)
    warp_sum_add(proj[1], totals, 2)
    dmd = grid_total(proj[2], words, 1, blocks, stalled_out)
    theta = line_step(load_coherent(totals, 1), load_coherent(totals, 2), dmd)
    dots = wp.vec2()
    for i in range(lane, n, threads):
        dots += init_row(i, theta, diag_inv, free, b, direction, x_out, w_out, r_out, u_out, p_out, s_out)
    warp_sum_add(dots[1], totals, 0)
    gamma = grid_total(dots[0], words, 2, blocks, stalled_out)
    return wp.vec2(gamma, load_coherent(totals, 0))


@wp.kernel
def cg_solve(
    # inputs: launch shape
    threads: int,
    blocks: int,
    # inputs: matrix
    matrix: BlockMatrix,
    pairs: Pairs,
    # inputs: system and limits
    diag_inv: wp.array(dtype=wp.mat33),
    free: wp.array(dtype=wp.int32),
    b: wp.array(dtype=wp.vec3),
    direction: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    tolerance: wp.array(dtype=float),
    max_iterations: wp.array(dtype=wp.int32),
    # synchronisation (zeroed by cg_solve_reset, as are w and s)
    words: wp.array(dtype=wp.uint64),
    totals: wp.array(dtype=float),
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
    """The whole solve in one persistent launch of ``blocks`` resident blocks (one thread on the CPU).

    The iteration of ``cg_update`` + ``cg_apply``, meeting at two grid barriers instead of launches.
    """
    lane = wp.tid()
    n = free.shape[0]
    own = own_chunk(0, lane, matrix)
    start = solve_start(
        lane, threads, blocks, 0, own, matrix, pairs, diag_inv, free, b, direction, mass, words, totals,
        x_out, r_out, u_out, p_out, s_out, w_out, stalled_out,
    )  # fmt: skip
    gamma = start[0]
    bz = start[1]
    tol2 = tolerance[0] * tolerance[0]
    max_k = max_iterations[0]
    k = int(0)
    gamma_prev = float(0.0)
    a_prev = float(0.0)
    while k < max_k and gamma > 0.0 and gamma > tol2 * bz:
        part = partial_product(lane, threads, 0, own, matrix, pairs, u_out, w_out)
        delta = grid_total(part, words, 3 + 2 * k, blocks, stalled_out)
        a, beta = step_sizes(k, gamma, gamma_prev, delta, a_prev)
        if a <= 0.0:
            break
        ru = float(0.0)
        for i in range(lane, n, threads):
            ru += update_row(i, a, beta, diag_inv, free, x_out, r_out, u_out, p_out, s_out, w_out)
        gamma_prev = gamma
        a_prev = a
        gamma = grid_total(ru, words, 4 + 2 * k, blocks, stalled_out)
        k += 1
    if lane == 0:
        record_solve(k, gamma, bz, tolerance[0], counts_out, residual_max_out)


@wp.kernel
def cg_solve_shared(
    threads: int,
    blocks: int,
    matrix: BlockMatrix,
    pairs: Pairs,
    diag_inv: wp.array(dtype=wp.mat33),
    free: wp.array(dtype=wp.int32),
    b: wp.array(dtype=wp.vec3),
    direction: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    tolerance: wp.array(dtype=float),
    max_iterations: wp.array(dtype=wp.int32),
    words: wp.array(dtype=wp.uint64),
    totals: wp.array(dtype=float),
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
    """``cg_solve`` with each thread's chunks held for the whole solve, where blocks of them fit in shared memory.

    Each thread keeps up to ``kernels.product.SHARED_SLOTS`` chunks of a gathered product, their blocks in its
    column of the block's shared tile and their rows and columns in registers (:func:`hold_chunks`), and its first
    coupling pair in registers (:func:`hold_pair`), so an iteration's product reads only the vector from global
    memory (:func:`shared_product`). Launched in blocks of :data:`SHARED_BLOCK` threads, one an SM (the tile takes
    most of its shared memory); CUDA only.
    """
    lane = wp.tid()
    n = free.shape[0]
    held = wp.tile_zeros(shape=(SHARED_ROWS, SHARED_BLOCK), dtype=wp.mat33, storage="shared")
    chunks = hold_chunks(held, lane, threads, matrix)
    pair = hold_pair(lane, blocks, pairs)
    own = own_chunk(0, lane, matrix)
    start = solve_start(
        lane, threads, blocks, 0, own, matrix, pairs, diag_inv, free, b, direction, mass, words, totals,
        x_out, r_out, u_out, p_out, s_out, w_out, stalled_out,
    )  # fmt: skip
    gamma = start[0]
    bz = start[1]
    tol2 = tolerance[0] * tolerance[0]
    max_k = max_iterations[0]
    k = int(0)
    gamma_prev = float(0.0)
    a_prev = float(0.0)
    while k < max_k and gamma > 0.0 and gamma > tol2 * bz:
        part = shared_product(held, chunks, pair, threads, lane % SHARED_BLOCK, pairs, u_out, w_out)
        delta = grid_total(part, words, 3 + 2 * k, blocks, stalled_out)
        a, beta = step_sizes(k, gamma, gamma_prev, delta, a_prev)
        if a <= 0.0:
            break
        ru = float(0.0)
        for i in range(lane, n, threads):
            ru += update_row(i, a, beta, diag_inv, free, x_out, r_out, u_out, p_out, s_out, w_out)
        gamma_prev = gamma
        a_prev = a
        gamma = grid_total(ru, words, 4 + 2 * k, blocks, stalled_out)
        k += 1
    if lane == 0:
        record_solve(k, gamma, bz, tolerance[0], counts_out, residual_max_out)


@wp.kernel
def cg_solve_held(
    # inputs: launch shape
    threads: int,
    blocks: int,
    pair_lanes: int,
    # inputs: matrix
    matrix: BlockMatrix,
    pairs: Pairs,
    # inputs: system and limits
    diag_inv: wp.array(dtype=wp.mat33),
    free: wp.array(dtype=wp.int32),
    b: wp.array(dtype=wp.vec3),
    direction: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    tolerance: wp.array(dtype=float),
    max_iterations: wp.array(dtype=wp.int32),
    # synchronisation (zeroed by cg_solve_reset, as are w and s)
    words: wp.array(dtype=wp.uint64),
    totals: wp.array(dtype=float),
    # outputs
    x_out: wp.array(dtype=wp.vec3),
    r_out: wp.array(dtype=wp.vec3),
    p_out: wp.array(dtype=wp.vec3),
    s_out: wp.array(dtype=wp.vec3),
    w_out: wp.array(dtype=wp.vec3),
    u2_out: wp.array(dtype=wp.vec3),
    q2_out: wp.array(dtype=wp.vec3),
    m3_out: wp.array(dtype=wp.vec3),
    counts_out: wp.array(dtype=wp.int32),
    residual_max_out: wp.array(dtype=float),
    stalled_out: wp.array(dtype=wp.int32),
):
    """``cg_solve`` with one grid barrier per iteration, where every chunk of the product has a thread.

    The iteration runs on u = M^-1 r, q = M^-1 s and m = M^-1 A u (q_k = m_k + beta q_{k-1},
    u_{k+1} = u_k - alpha q_k, gamma = u.M u), so a row's update needs only that row: after the barrier
    that delivers gamma_k and delta_k, each thread advances the rows it reads itself (:func:`advanced`) and
    goes straight on to its share of m_{k+1} and delta_{k+1} = u.A u. Coupling pairs take the last
    ``pair_lanes`` lanes, :data:`PAIR_LANES` to a pair. The thread of a row's first chunk keeps its x and p in
    registers and writes its u and q; u and q alternate between two buffers and m among three (read, written,
    zeroed), so no phase reads what it writes.
    """
    lane = wp.tid()
    n = free.shape[0]
    n_chunks = matrix.chunk_row.shape[0]
    own = own_chunk(1, lane, matrix)
    pair0 = threads - pair_lanes  # the pair blocks, at the end of the grid: a group of PAIR_LANES lanes per pair
    group = (lane - pair0) // PAIR_LANES
    groups = pair_lanes // PAIR_LANES
    live = live_pairs(pairs)
    corner = pair_corner(group, lane % PAIR_LANES, pairs)  # the group's first pair, held for the solve
    for i in range(lane, n, threads):  # the loop's buffers (u's first is the start's u), before its barriers
        u2_out[n + i] = wp.vec3()
        q2_out[i] = wp.vec3()
        q2_out[n + i] = wp.vec3()
        m3_out[i] = wp.vec3()
        m3_out[n + i] = wp.vec3()
        m3_out[2 * n + i] = wp.vec3()
    start = solve_start(
        lane, threads, blocks, 1, own, matrix, pairs, diag_inv, free, b, direction, mass, words, totals,
        x_out, r_out, u2_out, p_out, s_out, w_out, stalled_out,
    )  # fmt: skip
    gamma = start[0]
    bz = start[1]
    row = own.row
    D = diag_inv[row]
    first = lane == 0
    if lane > 0 and lane < n_chunks:
        first = matrix.chunk_row[lane - 1] != row
    owner = own.count > 0 and first and free[row] != 0
    A_ii = wp.mat33()
    x = wp.vec3()
    p = wp.vec3()
    if owner:
        A_ii = wp.inverse(D)
        x = x_out[row]
    tol2 = tolerance[0] * tolerance[0]
    max_k = max_iterations[0]
    k = int(0)
    j = int(0)  # phase 0 is the product of u_0 alone (a = beta = 0)
    a = float(0.0)
    beta = float(0.0)
    gamma_prev = float(0.0)
    a_prev = float(0.0)
    delta = float(0.0)
    while True:
        part = wp.vec2()
        if own.count > 0:
            u_row, q_row, u_old = advanced(row, n, j, a, beta, m3_out, q2_out, u2_out)
            u0 = advanced_u(own.cols[0], n, j, a, beta, m3_out, q2_out, u2_out)
            u1 = advanced_u(own.cols[1], n, j, a, beta, m3_out, q2_out, u2_out)
            u2 = advanced_u(own.cols[2], n, j, a, beta, m3_out, q2_out, u2_out)
            u3 = advanced_u(own.cols[3], n, j, a, beta, m3_out, q2_out, u2_out)
            acc = held_terms(own, u0, u1, u2, u3)
            wp.atomic_add(m3_out, (j % 3) * n + row, D * acc)
            part[0] = wp.dot(u_row, acc)
            if owner:
                u2_out[((j + 1) % 2) * n + row] = u_row
                q2_out[((j + 1) % 2) * n + row] = q_row
                m3_out[((j + 1) % 3) * n + row] = wp.vec3()
                p = u_old + beta * p
                x = x + a * p
                part[1] = wp.dot(u_row, A_ii * u_row)
        if lane >= pair0:  # whole blocks: the branch keeps every warp together
            for c in range(group, live, groups):
                if c == group:
                    part[0] += held_corner_phase(
                        corner.vert_a, corner.weight_a, corner.vert_b, corner.weight_b, corner.C, n, j, a, beta,
                        diag_inv, m3_out, q2_out, u2_out,
                    )  # fmt: skip
                else:
                    other = pair_corner(c, lane % PAIR_LANES, pairs)
                    part[0] += held_corner_phase(
                        other.vert_a, other.weight_a, other.vert_b, other.weight_b, other.C, n, j, a, beta,
                        diag_inv, m3_out, q2_out, u2_out,
                    )  # fmt: skip
        if j > 0:
            warp_sum_add(part[1], totals, 2 + j)
        delta = grid_total(part[0], words, 3 + j, blocks, stalled_out)
        if j > 0:
            gamma_prev = gamma
            a_prev = a
            gamma = load_coherent(totals, 2 + j)
            k += 1
        if not (k < max_k and gamma > 0.0 and gamma > tol2 * bz):
            break
        a, beta = step_sizes(k, gamma, gamma_prev, delta, a_prev)
        if a <= 0.0:
            break
        j = k + 1
    if owner:
        x_out[row] = x
    if lane == 0:
        record_solve(k, gamma, bz, tolerance[0], counts_out, residual_max_out)


HELD_WIDE_BLOCK = 384
"""Threads per block of :data:`cg_solve_held_wide`."""

cg_solve_held_wide = wp.kernel(
    cg_solve_held.func,
    name="cg_solve_held_wide",
    launch_bounds=(HELD_WIDE_BLOCK, 1),
    enable_cuda_smem_spilling=True,
)
"""``cg_solve_held`` in blocks of :data:`HELD_WIDE_BLOCK` threads, one block an SM: the registers it cannot keep at
that size spill to the SM's shared memory, so half as many chunks again as at 256 threads keep a thread each."""

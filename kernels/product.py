"""The block-matrix product of the CG kernels: chunks of a 3x3-block CSR matrix and matrix-free pairs.

The matrix is stored as its upper triangle. A chunk is at most a few entries of one row; the product either
gathers (a row's entries are its stored blocks and the mirrors of those above it: one atomic add per chunk
into its own row) or scatters (each stored block also adds its transpose into another row: an atomic per
block, half the reads), see ``warpfem.sim.cg.GATHER_MAX_ROWS``. A coupling term (pairs of points embedded in the
mesh, such as contacts) is applied by extra threads. A persistent solve whose every chunk has a thread of its
own keeps that chunk's columns and blocks in registers for the whole solve (:class:`OwnChunk`): an iteration
then loads only the vector.
"""

import warp as wp

from .grid import quad_sum

mat43 = wp.types.matrix(shape=(4, 3), dtype=wp.float32)
"""A pair's values at its four a (or b) vertices, one per row."""


@wp.func
def pair_terms(
    Ua: mat43,
    Ub: mat43,
    weights_a: wp.vec4,
    weights_b: wp.vec4,
    C: wp.mat33,
):
    """One pair's (J^T C J less its diagonal blocks) u, given u at its eight vertices (rows of Ua and Ub).

    ``J u = sum_k weights_a[k] Ua[k] - weights_b[k] Ub[k]`` is the pair's relative value. Returns the terms
    for the a and b vertices (rows of two 4x3 matrices) and the pair's share of u.w.
    """
    s = wp.vec3()
    for k in range(4):
        s += weights_a[k] * Ua[k] - weights_b[k] * Ub[k]
    Da = mat43()
    Db = mat43()
    dot = float(0.0)
    for k in range(4):
        da = weights_a[k] * (C * (s - weights_a[k] * Ua[k]))
        db = -weights_b[k] * (C * (s + weights_b[k] * Ub[k]))
        Da[k] = da
        Db[k] = db
        dot += wp.dot(Ua[k], da) + wp.dot(Ub[k], db)
    return Da, Db, dot


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
    """w += (J^T C J less its diagonal blocks) u for one pair (see :func:`pair_terms`); returns its u.w.

    The eight values of u are loaded once, before any atomic add: a load after an atomic add to a buffer
    that may alias ``u`` cannot be issued ahead of it, so reloading them in the scatter loop would chain
    eight dependent round trips to memory.
    """
    Ua = wp.matrix_from_rows(u[verts_a[0]], u[verts_a[1]], u[verts_a[2]], u[verts_a[3]])
    Ub = wp.matrix_from_rows(u[verts_b[0]], u[verts_b[1]], u[verts_b[2]], u[verts_b[3]])
    Da, Db, dot = pair_terms(Ua, Ub, weights_a, weights_b, C)
    for k in range(4):
        wp.atomic_add(w_out, verts_a[k], Da[k])
        wp.atomic_add(w_out, verts_b[k], Db[k])
    return dot


GROUP = 4
"""Entries of a chunk whose loads are issued together."""


@wp.func
def entry_term(valid: bool, slot: int, A: wp.mat33, u_c: wp.vec3) -> wp.vec3:
    """One entry's share of its row of A u: A u_c for a stored block (slot >= 0), A^T u_c for a mirrored one."""
    if not valid:
        return wp.vec3()
    if slot >= 0:
        return A * u_c
    return wp.transpose(A) * u_c


@wp.func
def stored(slot: int) -> int:
    """The stored block of an entry: ``slot`` itself, or ``-slot - 1`` for a mirrored entry."""
    return wp.where(slot >= 0, slot, -slot - 1)


@wp.struct
class BlockMatrix:
    """A product's symmetric 3x3-block matrix, cut into chunks: one kernel argument.

    Chunk i is the entries ``chunk_start[i]`` to ``chunk_end[i]`` of row ``chunk_row[i]``. Gathered
    (``gather`` != 0), an entry is a column and a slot (see :func:`chunk_gather`); scattered, ``entry_col``
    holds the stored blocks' columns and ``entry_slot`` is empty. ``values`` holds the stored blocks (the
    upper triangle).
    """

    chunk_row: wp.array(dtype=wp.int32)
    chunk_start: wp.array(dtype=wp.int32)
    chunk_end: wp.array(dtype=wp.int32)
    entry_col: wp.array(dtype=wp.int32)
    entry_slot: wp.array(dtype=wp.int32)
    values: wp.array(dtype=wp.mat33)
    gather: int


@wp.func
def chunk_gather(
    i: int,
    matrix: BlockMatrix,
    u: wp.array(dtype=wp.vec3),
    w_out: wp.array(dtype=wp.vec3),
) -> float:
    """w[row] += chunk i's share of row ``row`` of A u, gathered: one atomic add; returns its share of u.w.

    The product of systems up to ``warpfem.sim.cg.GATHER_MAX_ROWS`` rows.

    A row's entries are its stored blocks (the upper triangle, ``slot >= 0``) and the mirrors of the blocks
    stored in the rows above that have it as a column (``slot = -stored - 1``, applied transposed), so a
    chunk reads what it needs and adds once to its own row: no atomic add per block into other rows. Loads
    go in groups of :data:`GROUP`: columns and slots, then blocks and u at the columns.
    """
    row = matrix.chunk_row[i]
    first = matrix.chunk_start[i]
    end = matrix.chunk_end[i]
    u_row = u[row]
    acc = wp.vec3()
    for g in range(first, end, GROUP):
        k0 = wp.min(g, end - 1)
        k1 = wp.min(g + 1, end - 1)
        k2 = wp.min(g + 2, end - 1)
        k3 = wp.min(g + 3, end - 1)
        c0, s0 = matrix.entry_col[k0], matrix.entry_slot[k0]
        c1, s1 = matrix.entry_col[k1], matrix.entry_slot[k1]
        c2, s2 = matrix.entry_col[k2], matrix.entry_slot[k2]
        c3, s3 = matrix.entry_col[k3], matrix.entry_slot[k3]
        A0, u0 = matrix.values[stored(s0)], u[c0]
        A1, u1 = matrix.values[stored(s1)], u[c1]
        A2, u2 = matrix.values[stored(s2)], u[c2]
        A3, u3 = matrix.values[stored(s3)], u[c3]
        acc += entry_term(True, s0, A0, u0)
        acc += entry_term(g + 1 < end, s1, A1, u1)
        acc += entry_term(g + 2 < end, s2, A2, u2)
        acc += entry_term(g + 3 < end, s3, A3, u3)
    wp.atomic_add(w_out, row, acc)
    return wp.dot(u_row, acc)


@wp.func
def add_block(
    row: int, c: int, A: wp.mat33, u_c: wp.vec3, u_row: wp.vec3, acc: wp.vec3, w_out: wp.array(dtype=wp.vec3)
) -> wp.vec3:
    """One stored block (row, c) of a scattering chunk: returns acc + A u_c; adds A^T u_row to w[c] if c > row."""
    if c != row:
        wp.atomic_add(w_out, c, wp.transpose(A) * u_row)
    return acc + A * u_c


@wp.func
def chunk_scatter(
    i: int,
    matrix: BlockMatrix,
    u: wp.array(dtype=wp.vec3),
    w_out: wp.array(dtype=wp.vec3),
) -> float:
    """w += chunk i's stored blocks times u and their transposes (scattered with atomics); returns its u.w.

    The product of larger systems: each stored block is read once (half the traffic of the gather, which
    reads each off-diagonal block twice), at the cost of an atomic add per block into another row, which
    pays once the matrix outgrows the L2 cache. A chunk holds consecutive stored blocks of its row; loads go
    in groups of :data:`GROUP` ahead of the atomics (a load after an atomic add to a buffer that may alias
    ``u`` waits for it in program order).
    """
    row = matrix.chunk_row[i]
    first = matrix.chunk_start[i]
    end = matrix.chunk_end[i]
    u_row = u[row]
    acc = wp.vec3()
    for g in range(first, end, GROUP):
        k0 = wp.min(g, end - 1)
        k1 = wp.min(g + 1, end - 1)
        k2 = wp.min(g + 2, end - 1)
        k3 = wp.min(g + 3, end - 1)
        c0, c1, c2, c3 = matrix.entry_col[k0], matrix.entry_col[k1], matrix.entry_col[k2], matrix.entry_col[k3]
        A0, A1, A2, A3 = matrix.values[k0], matrix.values[k1], matrix.values[k2], matrix.values[k3]
        u0, u1, u2, u3 = u[c0], u[c1], u[c2], u[c3]
        acc = add_block(row, c0, A0, u0, u_row, acc, w_out)
        if g + 1 < end:
            acc = add_block(row, c1, A1, u1, u_row, acc, w_out)
        if g + 2 < end:
            acc = add_block(row, c2, A2, u2, u_row, acc, w_out)
        if g + 3 < end:
            acc = add_block(row, c3, A3, u3, u_row, acc, w_out)
    wp.atomic_add(w_out, row, acc)
    # u.(A u) over the stored triangle: 2 u_row.(A_rc u_c) off the diagonal, u_row.(A_rr u_row) on it
    diagonal = wp.where(matrix.entry_col[first] == row, wp.dot(u_row, matrix.values[first] * u_row), 0.0)
    return 2.0 * wp.dot(u_row, acc) - diagonal


@wp.func
def chunk_product(
    i: int,
    matrix: BlockMatrix,
    u: wp.array(dtype=wp.vec3),
    w_out: wp.array(dtype=wp.vec3),
) -> float:
    """Chunk i of the product, gathered or scattered.

    ``gather`` != 0: the chunk holds entries (see ``chunk_gather``); else ``entry_col`` holds the stored
    blocks' columns (see ``chunk_scatter``).
    """
    if matrix.gather != 0:
        return chunk_gather(i, matrix, u, w_out)
    return chunk_scatter(i, matrix, u, w_out)


@wp.struct
class Pairs:
    """The coupling pairs of a product: ``warpfem.sim.contacts.Coupling`` as one kernel argument.

    Pair c ties the point ``sum_k weights_a[c][k] x[verts_a[c][k]]`` to the point of ``verts_b`` and
    ``weights_b`` through ``matrix[c]``; the first ``count[0]`` (capped at the capacity) are live.
    """

    count: wp.array(dtype=wp.int32)
    verts_a: wp.array(dtype=wp.vec4i)
    weights_a: wp.array(dtype=wp.vec4)
    verts_b: wp.array(dtype=wp.vec4i)
    weights_b: wp.array(dtype=wp.vec4)
    matrix: wp.array(dtype=wp.mat33)


@wp.func
def live_pairs(pairs: Pairs) -> int:
    """The coupling pairs in use: the count, capped at the buffer's capacity."""
    return wp.min(pairs.count[0], pairs.matrix.shape[0])


@wp.func
def pair_product(
    c: int,
    pairs: Pairs,
    u: wp.array(dtype=wp.vec3),
    w_out: wp.array(dtype=wp.vec3),
) -> float:
    """w += coupling pair c's share of A u (c below ``live_pairs``); returns its u.w."""
    return embedded_product(
        pairs.verts_a[c], pairs.weights_a[c], pairs.verts_b[c], pairs.weights_b[c], pairs.matrix[c], u, w_out
    )


@wp.func
def first_pair(lane: int, threads: int, n_chunks: int) -> int:
    """The first coupling pair of a thread's share.

    Pairs start at the lane after the last chunk's (wrapping around), so they go to idle threads first rather
    than lengthening the chains of the threads that hold chunks.
    """
    return ((lane - n_chunks) % threads + threads) % threads


PAIR_LANES = 4
"""Threads per coupling pair in the held solve (``kernels.cg.cg_solve_held``): lane k of a pair's group takes
corner k of both its points, and the group sums the pair's relative value with register shuffles."""


@wp.struct
class PairCorner:
    """Corner k of a coupling pair: what lane k of the pair's group needs (see :data:`PAIR_LANES`).

    Attributes:
        vert_a: Point a's k-th vertex. weight_a: Its weight.
        vert_b: Point b's k-th vertex. weight_b: Its weight, negated (J u = sum of weight u over the corners).
        C: The pair's 3x3 matrix.
    """

    vert_a: int
    weight_a: float
    vert_b: int
    weight_b: float
    C: wp.mat33


@wp.func
def pair_corner(c: int, k: int, pairs: Pairs) -> PairCorner:
    """Corner ``k`` (0..3) of coupling pair ``c``; zero weights (it adds nothing) where ``c`` is not live."""
    corner = PairCorner()
    if c >= 0 and c < live_pairs(pairs):
        corner.vert_a = pairs.verts_a[c][k]
        corner.weight_a = pairs.weights_a[c][k]
        corner.vert_b = pairs.verts_b[c][k]
        corner.weight_b = -pairs.weights_b[c][k]
        corner.C = pairs.matrix[c]
    return corner


@wp.func
def pair_share(
    lane: int,
    threads: int,
    n_chunks: int,
    pairs: Pairs,
    u: wp.array(dtype=wp.vec3),
    w_out: wp.array(dtype=wp.vec3),
) -> float:
    """The calling thread's share of the pairs' w += A u and u.w (pairs strided over ``threads`` threads)."""
    dot = float(0.0)
    for c in range(first_pair(lane, threads, n_chunks), live_pairs(pairs), threads):
        dot += pair_product(c, pairs, u, w_out)
    return dot


OWN_CHUNK_ENTRIES = 4
"""The most entries a chunk held in registers (:class:`OwnChunk`) has."""


@wp.struct
class OwnChunk:
    """A thread's chunk of the gathered product, in registers for a whole solve (the blocks do not change).

    Attributes:
        row: The chunk's row.
        count: Its entries (at most :data:`OWN_CHUNK_ENTRIES`); 0 for a thread that owns no chunk.
        cols: The entries' columns (unused ones repeat the last).
        slots: The entries' slots (see :func:`chunk_gather`).
        a0: The first entry's block, as stored (a mirrored entry is applied transposed); a1, a2, a3 the next.
    """

    row: int
    count: int
    cols: wp.vec4i
    slots: wp.vec4i
    a0: wp.mat33
    a1: wp.mat33
    a2: wp.mat33
    a3: wp.mat33


@wp.func
def own_chunk(
    held: int,
    lane: int,
    matrix: BlockMatrix,
) -> OwnChunk:
    """Chunk ``lane`` of a gathered product (at most :data:`OWN_CHUNK_ENTRIES` entries per chunk), loaded once.

    A lane past the last chunk gets ``count = 0`` (it loads the last chunk but applies nothing), as does every
    lane when ``held`` is 0 (it loads nothing: the entries may not be a gather's).
    """
    c = OwnChunk()
    n_chunks = matrix.chunk_row.shape[0]
    if held == 0 or n_chunks == 0:
        return c
    i = wp.min(lane, n_chunks - 1)
    first = matrix.chunk_start[i]
    end = matrix.chunk_end[i]
    k1 = wp.min(first + 1, end - 1)
    k2 = wp.min(first + 2, end - 1)
    k3 = wp.min(first + 3, end - 1)
    c.row = matrix.chunk_row[i]
    c.count = wp.where(lane < n_chunks, end - first, 0)
    c.cols = wp.vec4i(matrix.entry_col[first], matrix.entry_col[k1], matrix.entry_col[k2], matrix.entry_col[k3])
    c.slots = wp.vec4i(matrix.entry_slot[first], matrix.entry_slot[k1], matrix.entry_slot[k2], matrix.entry_slot[k3])
    c.a0 = matrix.values[stored(c.slots[0])]
    c.a1 = matrix.values[stored(c.slots[1])]
    c.a2 = matrix.values[stored(c.slots[2])]
    c.a3 = matrix.values[stored(c.slots[3])]
    return c


@wp.func
def own_chunk_product(c: OwnChunk, u: wp.array(dtype=wp.vec3), w_out: wp.array(dtype=wp.vec3)) -> float:
    """w[row] += the held chunk's share of A u, as :func:`chunk_gather` (one round trip: u only); its u.w."""
    if c.count == 0:
        return 0.0
    u0, u1, u2, u3, u_row = u[c.cols[0]], u[c.cols[1]], u[c.cols[2]], u[c.cols[3]], u[c.row]
    acc = held_terms(c, u0, u1, u2, u3)
    wp.atomic_add(w_out, c.row, acc)
    return wp.dot(u_row, acc)


@wp.func
def held_terms(c: OwnChunk, u0: wp.vec3, u1: wp.vec3, u2: wp.vec3, u3: wp.vec3) -> wp.vec3:
    """The held chunk's share of its row of A u, given u at its four columns (unused ones ignored)."""
    acc = entry_term(True, c.slots[0], c.a0, u0)
    acc += entry_term(c.count > 1, c.slots[1], c.a1, u1)
    acc += entry_term(c.count > 2, c.slots[2], c.a2, u2)
    acc += entry_term(c.count > 3, c.slots[3], c.a3, u3)
    return acc


@wp.func
def partial_product(
    lane: int,
    threads: int,
    held: int,
    held_chunk: OwnChunk,
    matrix: BlockMatrix,
    pairs: Pairs,
    u: wp.array(dtype=wp.vec3),
    w_out: wp.array(dtype=wp.vec3),
) -> float:
    """The calling thread's share of w += A u and of u.w (w zeroed before; chunks and pairs strided over threads).

    With ``held`` set, every chunk has a thread of its own: ``held_chunk`` is this thread's (:func:`own_chunk`).
    Else the thread walks chunks ``lane``, ``lane + threads``, ... reading their entries and blocks.
    """
    n_chunks = matrix.chunk_row.shape[0]
    dot = float(0.0)
    if held != 0:
        dot = own_chunk_product(held_chunk, u, w_out)
    else:
        for i in range(lane, n_chunks, threads):
            dot += chunk_product(i, matrix, u, w_out)
    return dot + pair_share(lane, threads, n_chunks, pairs, u, w_out)


@wp.func
def advanced(
    c: int,
    n: int,
    j: int,
    a: float,
    beta: float,
    m3: wp.array(dtype=wp.vec3),
    q2: wp.array(dtype=wp.vec3),
    u2: wp.array(dtype=wp.vec3),
):
    """Row c at phase j of ``kernels.cg.cg_solve_held``: (u_{j}, q_{j-1}, u_{j-1}) from the buffers.

    q_{j-1} = m_{j-1} + beta q_{j-2} and u_j = u_{j-1} - a q_{j-1}, with m = M^-1 A u; every thread that
    needs row c computes it the same way, so no barrier separates the update from the product.
    """
    m = m3[((j + 2) % 3) * n + c]
    q_old = q2[(j % 2) * n + c]
    u_old = u2[(j % 2) * n + c]
    q = m + beta * q_old
    return u_old - a * q, q, u_old


@wp.func
def advanced_u(
    c: int,
    n: int,
    j: int,
    a: float,
    beta: float,
    m3: wp.array(dtype=wp.vec3),
    q2: wp.array(dtype=wp.vec3),
    u2: wp.array(dtype=wp.vec3),
) -> wp.vec3:
    """u_j of row c (see :func:`advanced`)."""
    u, q, u_old = advanced(c, n, j, a, beta, m3, q2, u2)
    return u


@wp.func
def held_corner_phase(
    vert_a: int,
    weight_a: float,
    vert_b: int,
    weight_b: float,
    C: wp.mat33,
    n: int,
    j: int,
    a: float,
    beta: float,
    diag_inv: wp.array(dtype=wp.mat33),
    m3: wp.array(dtype=wp.vec3),
    q2: wp.array(dtype=wp.vec3),
    u2: wp.array(dtype=wp.vec3),
) -> float:
    """One corner of a coupling pair at phase j (see :class:`kernels.product.PairCorner`), by its group's lane.

    The four lanes sum the pair's relative value s = J u_j (:func:`kernels.grid.quad_sum`); each adds
    M^-1 (J^T C J less its diagonal blocks) u_j at its two vertices into m_j, as ``kernels.product.pair_terms``
    does for a whole pair, and returns its share of u.A u.
    """
    ua = advanced_u(vert_a, n, j, a, beta, m3, q2, u2)
    ub = advanced_u(vert_b, n, j, a, beta, m3, q2, u2)
    s = quad_sum(weight_a * ua + weight_b * ub)
    da = weight_a * (C * (s - weight_a * ua))
    db = weight_b * (C * (s - weight_b * ub))
    out = (j % 3) * n
    wp.atomic_add(m3, out + vert_a, diag_inv[vert_a] * da)
    wp.atomic_add(m3, out + vert_b, diag_inv[vert_b] * db)
    return wp.dot(ua, da) + wp.dot(ub, db)


SHARED_BLOCK = 256
"""Threads per block of the shared-held solve (``kernels.cg.cg_solve_shared``): its tile has a column per thread."""

SHARED_SLOTS = 6
"""Chunks a thread of the shared-held solve keeps: ``lane``, ``lane + threads``, ... (at most this many)."""

SHARED_ROWS = wp.constant(SHARED_SLOTS * GROUP)
"""Rows of the shared-held solve's tile of blocks: a thread's chunk k takes rows ``k * GROUP`` to ``k * GROUP + 3``."""

SHARED_BYTES = SHARED_SLOTS * GROUP * SHARED_BLOCK * 36
"""Shared memory a block of the shared-held solve asks for (its tile of 3x3 float32 blocks)."""

slot_rows = wp.types.vector(length=SHARED_SLOTS, dtype=wp.int32)
"""A thread's held chunks' rows, -1 where it has no such chunk."""

slot_cols = wp.types.vector(length=SHARED_SLOTS * GROUP, dtype=wp.int32)
"""A thread's held chunks' columns, ``GROUP`` a chunk (unused entries repeat the chunk's row, with a zero block)."""


@wp.struct
class SlotChunks:
    """The columns of a thread's chunks of the shared-held solve, in registers for a whole solve."""

    rows: slot_rows
    cols: slot_cols


@wp.func
def hold_chunks(
    held: wp.tile(dtype=wp.mat33, shape=(SHARED_ROWS, SHARED_BLOCK)),
    lane: int,
    threads: int,
    matrix: BlockMatrix,
) -> SlotChunks:
    """Load a thread's chunks of a gathered product once: blocks into its column of ``held``, rows and columns returned.

    A mirrored entry's block is stored transposed, so the product reads every block the same way; an unused
    entry is a zero block at the chunk's row. Every thread of the block makes the same number of stores (each
    a block-wide barrier).
    """
    n_chunks = matrix.chunk_row.shape[0]
    column = lane % SHARED_BLOCK
    out = SlotChunks()
    for k in range(SHARED_SLOTS):
        i = lane + k * threads
        row = int(-1)
        first = int(0)
        end = int(0)
        if i < n_chunks:
            row = matrix.chunk_row[i]
            first = matrix.chunk_start[i]
            end = matrix.chunk_end[i]
        out.rows[k] = row
        for e in range(GROUP):
            A = wp.mat33()
            col = wp.max(row, 0)
            if first + e < end:
                slot = matrix.entry_slot[first + e]
                col = matrix.entry_col[first + e]
                A = matrix.values[stored(slot)]
                if slot < 0:
                    A = wp.transpose(A)
            out.cols[k * GROUP + e] = col
            held[k * GROUP + e, column] = A
    return out


@wp.func
def held_slot(
    held: wp.tile(dtype=wp.mat33, shape=(SHARED_ROWS, SHARED_BLOCK)),
    column: int,
    k: int,
    chunks: SlotChunks,
    u: wp.array(dtype=wp.vec3),
) -> wp.vec3:
    """Held chunk k's share of its row of A u (zero where the thread has no chunk k)."""
    b = k * GROUP
    acc = held[b, column] * u[chunks.cols[b]]
    acc += held[b + 1, column] * u[chunks.cols[b + 1]]
    acc += held[b + 2, column] * u[chunks.cols[b + 2]]
    acc += held[b + 3, column] * u[chunks.cols[b + 3]]
    return acc


slot_sums = wp.types.matrix(shape=(SHARED_SLOTS, 3), dtype=wp.float32)
"""A thread's held chunks' shares of A u, one per row."""


@wp.struct
class HeldPair:
    """A thread's first coupling pair in the shared-held solve, in registers for a whole solve (c = -1: none)."""

    c: int
    verts_a: wp.vec4i
    weights_a: wp.vec4
    verts_b: wp.vec4i
    weights_b: wp.vec4
    C: wp.mat33


@wp.func
def hold_pair(lane: int, blocks: int, pairs: Pairs) -> HeldPair:
    """The first pair of a thread of the shared-held solve: thread t of block b takes pair ``t * blocks + b``.

    Pairs spread over every block this way (each takes a share), where consecutive pairs on consecutive
    threads would load a few SMs with all of them while the grid barrier waits for those.
    """
    held = HeldPair()
    held.c = (lane % SHARED_BLOCK) * blocks + lane // SHARED_BLOCK
    if held.c >= live_pairs(pairs):
        held.c = -1
        return held
    held.verts_a = pairs.verts_a[held.c]
    held.weights_a = pairs.weights_a[held.c]
    held.verts_b = pairs.verts_b[held.c]
    held.weights_b = pairs.weights_b[held.c]
    held.C = pairs.matrix[held.c]
    return held


@wp.func
def shared_product(
    held: wp.tile(dtype=wp.mat33, shape=(SHARED_ROWS, SHARED_BLOCK)),
    chunks: SlotChunks,
    pair: HeldPair,
    threads: int,
    column: int,
    pairs: Pairs,
    u: wp.array(dtype=wp.vec3),
    w_out: wp.array(dtype=wp.vec3),
) -> float:
    """:func:`partial_product` from the held chunks and pair: the chunks' loads, the pairs, then the chunks' adds.

    Pairs past a thread's first (``pair.c + threads``, ...) are read as in the two-barrier solve. A load
    after an atomic add to a buffer that may alias ``u`` waits for it, so the chunks' adds come last.
    """
    sums = slot_sums()
    dot = float(0.0)
    for k in range(SHARED_SLOTS):
        acc = held_slot(held, column, k, chunks, u)
        sums[k] = acc
        row = chunks.rows[k]
        dot += wp.where(row >= 0, wp.dot(u[wp.max(row, 0)], acc), 0.0)
    if pair.c >= 0:
        dot += embedded_product(pair.verts_a, pair.weights_a, pair.verts_b, pair.weights_b, pair.C, u, w_out)
        for c in range(pair.c + threads, live_pairs(pairs), threads):
            dot += pair_product(c, pairs, u, w_out)
    for k in range(SHARED_SLOTS):
        if chunks.rows[k] >= 0:
            wp.atomic_add(w_out, chunks.rows[k], sums[k])
    return dot

"""Block-Jacobi preconditioned conjugate gradients on the device, capturable as one CUDA graph.

The iteration (Chronopoulos-Gear PCG, two launches per iteration: see :mod:`warpfem.kernels.cg`) runs
under ``wp.capture_while`` on a device-side condition, ``unroll`` iterations per check, so the same code
gives a fixed iteration count (tolerance 0) or iteration to a tolerance, with no host synchronisation on
CUDA. The tolerance and the iteration count live in device arrays: changing them needs no new capture.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import warp as wp

from warpfem.kernels import cg as K
from warpfem.kernels import deflation as KD
from warpfem.kernels.product import (
    OWN_CHUNK_ENTRIES,
    PAIR_LANES,
    SHARED_BLOCK,
    SHARED_BYTES,
    SHARED_SLOTS,
    BlockMatrix,
    Pairs,
)
from warpfem.sim.contacts import Coupling
from warpfem.sim.deflation import RigidDeflation

BLOCK = 256
"""Threads per block of the kernels that reduce dot products."""

# Where a block gets less shared memory than cg_solve_shared's tile (GPUs before the H100 class), Warp warns at every
# load of the CG module that it could not size the kernel; the solver never launches it there (CGSolver.shared).
warnings.filterwarnings("ignore", message=r"Failed to configure dynamic shared memory for kernel 'cg_solve_shared'")

CHUNK = {"cuda": 4, "cpu": 64}
"""Nonzero blocks per thread of the matrix product, per device kind (the CPU runs one thread at a time)."""

PAIR_THREADS = 2048
"""Threads of the product that apply the coupling pairs (each strides over the live ones)."""

MODES = ("grid", "launches")
"""How a solve runs: one persistent launch meeting at grid barriers, or two launches per iteration."""

PRODUCTS = ("gather", "scatter")
"""How the matrix product runs: each row gathers its blocks and their mirrors (no atomic per block), or
each stored block also scatters its transpose into another row with an atomic add (half the reads)."""

HELD_PAIR_BLOCKS = 4
"""The fewest blocks the held solve gives its coupling pairs where they have that many
(:data:`kernels.product.PAIR_LANES` lanes a pair: 256 pairs at once in blocks of 256; more take turns). Chosen by
measurement on an H100 (see docs/decisions.md): one block is too few for a contact-heavy scene, and more gain
nothing measurable in the paper's scenes."""

HELD_PAIR_SHARE = 8
"""Blocks of chunks per block of pairs above :data:`HELD_PAIR_BLOCKS`, within the SMs the chunks leave: contacts
grow with the bodies, and a pair group that takes turns over several pairs holds every block up at each barrier.
Chosen by measurement on an H200 (see docs/decisions.md)."""

SHARED_SLACK = 1024
"""Shared memory a block of ``kernels.cg.cg_solve_shared`` needs beyond its tile (the grid barrier's word)."""

GATHER_MAX_ROWS = 131_072
"""The largest system (rows) whose product gathers by default on CUDA; larger ones, and all on the CPU
(one thread, where an atomic add costs no more than a store), scatter. Chosen by measurement on an H100
(see docs/decisions.md): gathering avoids one atomic per block but reads every off-diagonal block twice,
which loses once the matrix outgrows the L2 cache."""

DEFAULT_MODE = "grid"
"""The path a solve takes unless told: "grid", on every device and size. Chosen by measurement on an H100
(see docs/decisions.md): a grid barrier costs less than a kernel launch, which matters most on small,
latency-bound systems, and with its release/acquire arrival it keeps up on large ones too."""


CAP_SLACK = K.CAP_SLACK
"""A final residual this much above the tolerance (float32 rounding aside) means CG stopped at its cap."""


@dataclass(frozen=True)
class CGStats:
    """What the solves since the last :meth:`CGSolver.read_stats` did.

    Attributes:
        solves: Number of solves.
        iterations: Total iterations over those solves.
        residual_max: Largest final relative residual sqrt(r.M^-1 r / b.M^-1 b).
        short: Solves that stopped at their cap above the tolerance.
    """

    solves: int
    iterations: int
    residual_max: float
    short: int = 0


def _check_options(mode: str, grid_blocks: int | None, product: str | None) -> None:
    """Raise ValueError for an unknown solve mode or product, or fewer than one grid block."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    if grid_blocks is not None and grid_blocks < 1:
        raise ValueError(f"grid_blocks must be at least 1, got {grid_blocks}")
    if product not in (None, *PRODUCTS):
        raise ValueError(f"product must be one of {PRODUCTS} or None, got {product!r}")


def _no_coupling(device) -> Coupling:
    """An empty matrix-free term: no pairs, and a count of zero."""
    zero = dict(shape=0, device=device)
    return Coupling(
        wp.zeros(1, dtype=wp.int32, device=device),
        wp.zeros(dtype=wp.vec4i, **zero),
        wp.zeros(dtype=wp.vec4, **zero),
        wp.zeros(dtype=wp.vec4i, **zero),
        wp.zeros(dtype=wp.vec4, **zero),
        wp.zeros(dtype=wp.mat33, **zero),
    )


class CGSolver:
    """Solves A x = b for a 3x3-block CSR matrix with a fixed structure.

    Args:
        row_start: (n+1) int32 row offsets.
        cols: (nnz) int32 block columns.
        free: (n) int32, 0 for rows held at their initial value.
        max_iterations: Capacity: the most iterations any solve may be asked for.
        device: Warp device.
        coupling: A matrix-free term of A applied with every product, or None.
        unroll: Iterations per convergence check of the device-side loop (each check is a graph node and a
            launch; iterations past convergence inside a check do nothing).
        mode: "grid": the whole solve as one persistent launch of at most one block per SM, the blocks meeting
            at grid-wide barriers (one thread on the CPU, where the loop then runs inside the kernel, not from
            Python); "launches": two launches per iteration under ``wp.capture_while``. None:
            :data:`DEFAULT_MODE`.
        grid_blocks: Blocks of the "grid" mode on CUDA; None: enough for a thread per row or product chunk,
            plus one for the coupling pairs if any, at most one per SM (the barriers need every block
            resident).
        product: "gather" or "scatter" (:data:`PRODUCTS`); None: gather on CUDA up to :data:`GATHER_MAX_ROWS`
            rows, else scatter.
        hold_chunks: Let a "grid" solve whose gathered product has a thread for every chunk keep each
            chunk's columns and blocks in registers for the whole solve and meet at one barrier per iteration
            (``kernels.cg.cg_solve_held``; the ``held`` attribute says whether it does), and one with more chunks
            keep each thread's few in shared memory where the device has room (``kernels.cg.cg_solve_shared``;
            the ``shared`` attribute); False: the two-barrier solve that reads them every iteration (for tests
            of that path).
        chunk: Nonzero blocks per thread of the product; None: :data:`CHUNK` for the device kind.
    """

    def __init__(
        self,
        row_start: wp.array,
        cols: wp.array,
        free: wp.array,
        max_iterations: int,
        device,
        coupling: Coupling | None = None,
        unroll: int = 4,
        mode: str | None = None,
        grid_blocks: int | None = None,
        product: str | None = None,
        hold_chunks: bool = True,
        chunk: int | None = None,
    ) -> None:
        self.device = wp.get_device(device)
        self.free = free
        self.unroll = int(unroll)
        n = free.shape[0]
        self.mode = mode or DEFAULT_MODE
        _check_options(self.mode, grid_blocks, product)
        # the CPU runs the product on one thread, where atomic adds cost no more than stores: half the reads win
        gather_default = self.device.is_cuda and n <= GATHER_MAX_ROWS
        self.product = product or ("gather" if gather_default else "scatter")
        self.padded = -(-n // BLOCK) * BLOCK  # whole blocks for the tile reductions
        self.capacity = int(max_iterations)
        self.chunk = chunk or CHUNK["cuda" if self.device.is_cuda else "cpu"]
        chunks = self._lay_out_product(row_start, cols, n)
        coupling = coupling if coupling is not None else _no_coupling(self.device)
        self.pairs = Pairs()
        self.pairs.count = coupling.count
        self.pairs.verts_a, self.pairs.weights_a = coupling.verts_a, coupling.weights_a
        self.pairs.verts_b, self.pairs.weights_b = coupling.verts_b, coupling.weights_b
        self.pairs.matrix = coupling.matrix
        """The coupling's contact pairs as the kernels read them (empty without a coupling)."""
        # one thread per chunk, then up to PAIR_THREADS threads striding over the live pairs
        threads = chunks + min(coupling.matrix.shape[0], PAIR_THREADS)
        self._apply_threads = threads
        self._apply_dim = max(BLOCK, -(-threads // BLOCK) * BLOCK)
        self._allocate(n)
        self._size_grid(n, chunks, coupling.matrix.shape[0], grid_blocks, hold_chunks)
        self._plans: dict[tuple, tuple[list, list, list]] = {}
        self.configure(max_iterations, 0.0)

    def _lay_out_product(self, row_start: wp.array, cols: wp.array, n: int) -> int:
        """The product's entries (gathered rows, or the stored blocks) cut into chunks; returns how many chunks."""
        starts, cols_host = row_start.numpy(), cols.numpy()
        if self.product == "gather":
            # each row's entries: its stored (upper) blocks, then the mirrors of the blocks above it
            slot_row = np.repeat(np.arange(n, dtype=np.int32), np.diff(starts))
            mirrored = np.flatnonzero(cols_host != slot_row)
            entry_row = np.concatenate([slot_row, cols_host[mirrored]])
            order = np.argsort(entry_row, kind="stable")
            entry_col = np.concatenate([cols_host, slot_row[mirrored]])[order]
            entry_slot = np.concatenate([np.arange(len(cols_host)), -mirrored - 1])[order]
            starts = np.concatenate([[0], np.cumsum(np.bincount(entry_row, minlength=n))])
            self.entry_col = wp.array(entry_col.astype(np.int32), dtype=wp.int32, device=self.device)
            self.entry_slot = wp.array(entry_slot.astype(np.int32), dtype=wp.int32, device=self.device)
        else:  # chunks of each row's stored blocks
            self.entry_col = cols
            self.entry_slot = wp.zeros(0, dtype=wp.int32, device=self.device)
        sizes = -(-np.diff(starts) // self.chunk)
        rows = np.repeat(np.arange(n, dtype=np.int32), sizes)
        first = np.repeat(starts[:-1], sizes) + self.chunk * (
            np.arange(len(rows)) - np.repeat(np.cumsum(sizes) - sizes, sizes)
        )
        last = np.minimum(first + self.chunk, np.repeat(starts[1:], sizes))
        self.chunk_row = wp.array(rows, dtype=wp.int32, device=self.device)
        self.chunk_start = wp.array(first.astype(np.int32), dtype=wp.int32, device=self.device)
        self.chunk_end = wp.array(last.astype(np.int32), dtype=wp.int32, device=self.device)
        return len(rows)

    def _allocate(self, n: int) -> None:
        """The solve's vectors, its per-iteration scalars and counters, and the grid solve's sums and barriers."""
        dev = self.device
        self.r = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.u = wp.zeros_like(self.r)
        self.p = wp.zeros_like(self.r)
        self.s = wp.zeros_like(self.r)
        self.w = wp.zeros_like(self.r)
        slots = self.capacity + self.unroll + 2
        self.gamma = wp.zeros(slots, dtype=float, device=dev)
        self.delta = wp.zeros_like(self.gamma)
        self.alpha = wp.zeros_like(self.gamma)
        self.bz = wp.zeros(1, dtype=float, device=dev)
        self.scratch = wp.zeros(1, dtype=float, device=dev)
        self.project = wp.zeros(3, dtype=float, device=dev)  # d.(b - A x), d.A d, d.M d
        self.no_direction = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.no_mass = wp.zeros(n, dtype=float, device=dev)
        self.iteration = wp.zeros(1, dtype=wp.int32, device=dev)
        self.done = wp.zeros(1, dtype=wp.int32, device=dev)
        self.cond = wp.zeros(1, dtype=wp.int32, device=dev)
        self.tolerance = wp.zeros(1, dtype=float, device=dev)
        self.max_iterations = wp.zeros(1, dtype=wp.int32, device=dev)
        self.counts = wp.zeros(3, dtype=wp.int32, device=dev)  # solves, iterations, stopped short
        self.residual_max = wp.zeros(1, dtype=float, device=dev)
        # the grid solve's side sums (three, and gamma per iteration where held) and barriers with their sums
        # (kernels.grid.grid_total): three to start, then two per iteration (one where held, plus one)
        self.totals = wp.zeros(3 + self.capacity, dtype=float, device=dev)
        self.words = wp.zeros(4 + 2 * self.capacity, dtype=wp.uint64, device=dev)
        self.stalled = wp.zeros(1, dtype=wp.int32, device=dev)

    def _size_grid(self, n: int, chunks: int, pairs_capacity: int, grid_blocks: int | None, hold_chunks: bool) -> None:
        """The grid solve's blocks, and whether it holds each thread's chunk in registers (``held``).

        Where every chunk has a thread, the grid solve keeps each thread's chunk in registers for the whole
        solve (``cg_solve_held``): an iteration loads only the vector and meets at one barrier instead of two.
        It tries blocks of :data:`BLOCK` threads, then of ``HELD_WIDE_BLOCK`` (``cg_solve_held_wide``); the
        coupling pairs get :data:`HELD_PAIR_BLOCKS` blocks, or one per :data:`HELD_PAIR_SHARE` blocks of chunks
        where the SMs the chunks leave allow, and no more than their capacity fills. Where no held solve fits,
        the two-barrier solve keeps up to ``kernels.product.SHARED_SLOTS`` chunks a thread in shared memory
        (``shared``) if the device gives a block room for them.
        """
        holdable = (
            hold_chunks
            and self.device.is_cuda
            and self.mode == "grid"
            and self.product == "gather"
            and self.chunk <= OWN_CHUNK_ENTRIES
        )
        self.grid_block = BLOCK
        """Threads per block of the grid solve's launch."""
        self.held_kernel = None
        """The held solve's kernel (``cg_solve_held`` or, for more chunks, ``cg_solve_held_wide``), or None."""
        self.shared = False
        """Whether the two-barrier solve holds each thread's chunks, their blocks in shared memory
        (``kernels.cg.cg_solve_shared``): where the chunks outnumber the threads but fit the SMs' shared memory."""
        if not self.device.is_cuda:
            self.grid_blocks, self.grid_threads, self.pair_lanes = 1, 1, 0
            return
        # the held solve's coupling pairs take blocks of their own at the end of the grid, PAIR_LANES lanes a pair
        held = ((BLOCK, K.cg_solve_held), (K.HELD_WIDE_BLOCK, K.cg_solve_held_wide)) if holdable else ()
        for block, kernel in held:
            chunk_blocks = -(-max(n, chunks, 1) // block)
            share = min(-(-chunk_blocks // HELD_PAIR_SHARE), self.device.sm_count - chunk_blocks)
            pair_blocks = min(max(HELD_PAIR_BLOCKS, share), -(-pairs_capacity * PAIR_LANES // block))
            wanted = grid_blocks if grid_blocks is not None else chunk_blocks + pair_blocks
            blocks = max(1, min(int(wanted), self.device.sm_count))
            if (blocks - pair_blocks) * block >= chunks:
                self.grid_block, self.held_kernel, self.grid_blocks = block, kernel, blocks
                self.pair_lanes = pair_blocks * block
                break
        else:
            # a thread per row or chunk, and a block more for the pairs (they start past the chunks)
            wanted = (
                grid_blocks if grid_blocks is not None else -(-max(n, chunks, 1) // BLOCK) + int(pairs_capacity > 0)
            )
            self.grid_blocks = max(1, min(int(wanted), self.device.sm_count))
            self.pair_lanes = 0
            self.shared = (
                holdable
                and self.grid_block == SHARED_BLOCK
                and self.device.max_shared_memory_per_block >= SHARED_BYTES + SHARED_SLACK
                and self.grid_blocks * SHARED_BLOCK * SHARED_SLOTS >= chunks
            )
        self.grid_threads = self.grid_blocks * self.grid_block
        if self.held:  # the one-barrier iteration's vectors: u and q = M^-1 s in two buffers, m = M^-1 A u in three
            self.u2 = wp.zeros(2 * n, dtype=wp.vec3, device=self.device)
            self.q2 = wp.zeros(2 * n, dtype=wp.vec3, device=self.device)
            self.m3 = wp.zeros(3 * n, dtype=wp.vec3, device=self.device)

    @property
    def held(self) -> bool:
        """Whether the grid solve holds each thread's chunk in registers (:attr:`held_kernel` runs it)."""
        return self.held_kernel is not None

    def configure(self, max_iterations: int, tolerance: float) -> None:
        """Set the iteration cap and relative tolerance (0: always run ``max_iterations``).

        Writes device arrays only, so a captured graph picks the new values up. Call outside a capture.
        """
        if not 0 < max_iterations <= self.capacity:
            raise ValueError(f"max_iterations must be in 1..{self.capacity}, got {max_iterations}")
        if not 0.0 <= tolerance < 1.0:
            raise ValueError(f"tolerance must be in [0, 1), got {tolerance}")
        self.max_iterations.assign(np.array([max_iterations], dtype=np.int32))
        self.tolerance.assign(np.array([tolerance], dtype=np.float32))
        self.limits = (int(max_iterations), float(tolerance))
        """The cap and tolerance as set (host copies, for reports)."""

    def _matrix(self, values: wp.array) -> BlockMatrix:
        """The product kernels' matrix argument: the chunk table and entries with the blocks ``values``."""
        matrix = BlockMatrix()
        matrix.chunk_row, matrix.chunk_start, matrix.chunk_end = self.chunk_row, self.chunk_start, self.chunk_end
        matrix.entry_col, matrix.entry_slot = self.entry_col, self.entry_slot
        matrix.values = values
        matrix.gather = int(self.product == "gather")
        return matrix

    def _apply(
        self, values: wp.array, u: wp.array, gate: int, step: int, dot_out: wp.array, w_out: wp.array | None = None
    ):
        """The launch of w += A u (``w_out``, default w, zeroed before), u.w into ``dot_out[iteration + step]``."""
        return wp.launch(
            K.cg_apply,
            dim=self._apply_dim,
            block_dim=BLOCK,
            inputs=[
                self._apply_threads,
                self._matrix(values),
                self.pairs,
                u,
                gate,
                self.iteration,
                step,
                self.gamma,
                self.bz,
                self.tolerance,
                self.max_iterations,
            ],
            outputs=[self.w if w_out is None else w_out, dot_out],
            device=self.device,
            record_cmd=True,
        )

    def _plan(
        self,
        values: wp.array,
        diag_inv: wp.array,
        b: wp.array,
        x: wp.array,
        direction: wp.array,
        mass: wp.array,
        deflation: RigidDeflation | None,
    ) -> tuple[list, list, list]:
        """The recorded launches of a solve: before the loop, one loop body (none: no loop), after it.

        A deflated solve is launched (``kernels.deflation`` has no persistent form).

        Replaying recorded launches skips the argument packing of ``wp.launch``, which counts on the CPU,
        where every iteration is launched from Python.
        """
        if deflation is None and self.mode == "grid":
            return self._plan_grid(values, diag_inv, b, x, direction, mass), [], []
        before = self._plan_start(values, diag_inv, b, x, direction, mass, deflation)
        return before, self._plan_body(values, diag_inv, x, deflation), self._plan_finish()

    def _deflation_start(self, diag_inv: wp.array, deflation: RigidDeflation) -> list:
        """The start's u and r.u with the deflated bodies' rigid motions taken out (``kernels.deflation``)."""
        n, dev = self.free.shape[0], self.device
        d = deflation.arg()
        scalars = [self.iteration, -1, self.gamma, self.bz, self.tolerance, self.max_iterations, self.alpha]
        options = dict(dim=self.padded, block_dim=BLOCK, device=dev, record_cmd=True)
        return [
            wp.launch(KD.deflation_start_sums, inputs=[n, self.free, self.r, d], **options),
            wp.launch(
                KD.deflation_jacobi, inputs=[n, self.free, diag_inv, self.r, d, *scalars], outputs=[self.u], **options
            ),
            wp.launch(
                KD.deflation_project,
                inputs=[n, self.free, diag_inv, self.r, d, *scalars],
                outputs=[self.u, self.gamma],
                **options,
            ),
        ]

    def _deflation_update(self, update: list, vectors: list, step: int, deflation: RigidDeflation) -> list:
        """An iteration's update with the sums of its new r, then u and r.u without the rigid motions."""
        n, dev = self.free.shape[0], self.device
        d = deflation.arg()
        diag_inv = update[1]
        scalars = [self.iteration, step, self.gamma, self.bz, self.tolerance, self.max_iterations, self.alpha]
        options = dict(dim=self.padded, block_dim=BLOCK, device=dev, record_cmd=True)
        return [
            wp.launch(KD.deflation_update, inputs=[*update, d], outputs=[self.alpha, self.done, *vectors], **options),
            wp.launch(
                KD.deflation_jacobi, inputs=[n, self.free, diag_inv, self.r, d, *scalars], outputs=[self.u], **options
            ),
            wp.launch(
                KD.deflation_project,
                inputs=[n, self.free, diag_inv, self.r, d, *scalars],
                outputs=[self.u, self.gamma],
                **options,
            ),
        ]

    def _plan_grid(
        self, values: wp.array, diag_inv: wp.array, b: wp.array, x: wp.array, direction: wp.array, mass: wp.array
    ) -> list:
        """The grid solve: a reset, then the whole solve as one persistent launch (held or not)."""
        n, dev, threads = self.free.shape[0], self.device, self.grid_threads
        reset = wp.launch(
            K.cg_solve_reset,
            dim=max(n, self.words.shape[0]),
            inputs=[n],
            outputs=[self.w, self.s, self.totals, self.words],
            device=dev,
            record_cmd=True,
        )
        shape = [threads, self.grid_blocks]
        system = [self._matrix(values), self.pairs, diag_inv, self.free, b, direction, mass]
        limits = [self.tolerance, self.max_iterations, self.words, self.totals]
        stats = [self.counts, self.residual_max, self.stalled]
        if self.held:
            kernel = self.held_kernel
            shape.append(self.pair_lanes)
            outputs = [x, self.r, self.p, self.s, self.w, self.u2, self.q2, self.m3, *stats]
        else:
            kernel = K.cg_solve_shared if self.shared else K.cg_solve
            outputs = [x, self.r, self.u, self.p, self.s, self.w, *stats]
        solve = wp.launch(
            kernel,
            dim=threads,
            block_dim=self.grid_block if dev.is_cuda else 1,
            inputs=[*shape, *system, *limits],
            outputs=outputs,
            device=dev,
            record_cmd=True,
        )
        return [reset, solve]

    def _plan_start(
        self,
        values: wp.array,
        diag_inv: wp.array,
        b: wp.array,
        x: wp.array,
        direction: wp.array,
        mass: wp.array,
        deflation: RigidDeflation | None = None,
    ) -> list:
        """The launched solve's start: reset, the start's projection along ``direction``, r, u, p and the check.

        With ``deflation``, first its factors, and u and r.u without the rigid motions (:meth:`_deflation_start`).
        """
        n, dev = self.free.shape[0], self.device
        limits = [self.gamma, self.bz, self.tolerance, self.max_iterations]
        scalars = [self.w, self.s, self.gamma, self.delta, self.bz, self.scratch, self.project, self.iteration]
        return [
            *(deflation.factor_launches() if deflation is not None else []),
            wp.launch(
                K.cg_reset,
                dim=max(self.padded, self.gamma.shape[0]),
                inputs=[n],
                outputs=[*scalars, self.done],
                device=dev,
                record_cmd=True,
            ),
            self._apply(values, x, 0, 0, self.scratch),
            self._apply(values, direction, 0, 0, self.scratch, self.s),
            wp.launch(
                K.cg_project,
                dim=self.padded,
                block_dim=BLOCK,
                inputs=[n, self.free, b, direction, mass, self.w, self.s],
                outputs=[self.project],
                device=dev,
                record_cmd=True,
            ),
            wp.launch(
                K.cg_init,
                dim=self.padded,
                block_dim=BLOCK,
                inputs=[n, diag_inv, self.free, b, direction, self.project],
                outputs=[x, self.w, self.r, self.u, self.p, self.s, self.gamma, self.bz],
                device=dev,
                record_cmd=True,
            ),
            *(self._deflation_start(diag_inv, deflation) if deflation is not None else []),
            self._apply(values, self.u, 1, 0, self.delta),
            wp.launch(K.cg_start, dim=1, inputs=limits, outputs=[self.cond], device=dev, record_cmd=True),
        ]

    def _plan_body(
        self, values: wp.array, diag_inv: wp.array, x: wp.array, deflation: RigidDeflation | None = None
    ) -> list:
        """One pass of the launched solve's loop: ``unroll`` iterations and a check.

        An iteration is an update and a product, and with ``deflation`` u made without the rigid motions
        between them.
        """
        n, dev = self.free.shape[0], self.device
        limits = [self.gamma, self.bz, self.tolerance, self.max_iterations]
        vectors = [x, self.r, self.u, self.p, self.s, self.w]
        body = []
        for step in range(self.unroll):
            update = [n, diag_inv, self.iteration, step, self.gamma, self.delta, *limits[1:], self.free]
            if deflation is None:
                body.append(
                    wp.launch(
                        K.cg_update,
                        dim=self.padded,
                        block_dim=BLOCK,
                        inputs=update,
                        outputs=[self.alpha, self.done, *vectors, self.gamma],
                        device=dev,
                        record_cmd=True,
                    )
                )
            else:
                body.extend(self._deflation_update(update, vectors, step, deflation))
            body.append(self._apply(values, self.u, 1, step + 1, self.delta))
        body.append(
            wp.launch(
                K.cg_advance,
                dim=1,
                inputs=[self.unroll, *limits],
                outputs=[self.iteration, self.cond],
                device=dev,
                record_cmd=True,
            )
        )
        return body

    def _plan_finish(self) -> list:
        """The launched solve's end: its statistics."""
        return [
            wp.launch(
                K.cg_finish,
                dim=1,
                inputs=[self.gamma, self.bz, self.done, self.tolerance],
                outputs=[self.counts, self.residual_max],
                device=self.device,
                record_cmd=True,
            )
        ]

    def solve(
        self,
        values: wp.array,
        diag_inv: wp.array,
        b: wp.array,
        x: wp.array,
        direction: wp.array | None = None,
        mass: wp.array | None = None,
        deflation: RigidDeflation | None = None,
    ) -> None:
        """Solve ``A x = b``; ``diag_inv`` holds the inverse diagonal blocks.

        A is the block matrix ``values`` on the solver's pattern plus the coupling term, if any. CG starts
        from the ``x`` given, moved along ``direction`` (zero on pinned rows; None: not moved) by the step
        that minimises the A-norm error along it, clamped to [0, 1], if the direction is smooth: d.A d at
        most ``kernels.cg.SMOOTH`` times d.M d with M the diagonal of ``mass`` (per row, kg; needed with a
        direction). With ``deflation`` (bound to the step), the deflated bodies' rigid motions are left as the
        start has them (:mod:`warpfem.kernels.deflation`): the rigid correction after the solve sets them.
        """
        if direction is not None and mass is None:
            raise ValueError("a start direction needs the rows' masses")
        direction = self.no_direction if direction is None else direction
        mass = self.no_mass if mass is None else mass
        self._run(self._plan_for(values, diag_inv, b, x, direction, mass, deflation))

    def _plan_for(
        self,
        values: wp.array,
        diag_inv: wp.array,
        b: wp.array,
        x: wp.array,
        direction: wp.array,
        mass: wp.array,
        deflation: RigidDeflation | None,
    ) -> tuple[list, list, list]:
        """The recorded plan of a solve with these arguments, recorded on first use."""
        key = (values.ptr, diag_inv.ptr, b.ptr, x.ptr, direction.ptr, mass.ptr, deflation.key if deflation else None)
        if key not in self._plans:
            if len(self._plans) >= 8:
                self._plans.clear()
            self._plans[key] = self._plan(values, diag_inv, b, x, direction, mass, deflation)
        return self._plans[key]

    def _run(self, plan: tuple[list, list, list]) -> None:
        """Launch a recorded plan: before, the loop under ``wp.capture_while``, after."""
        before, body, after = plan
        for launch in before:
            launch.launch()
        if body:

            def iterate() -> None:
                for launch in body:
                    launch.launch()

            wp.capture_while(self.cond, iterate)
        for launch in after:
            launch.launch()

    def read_stats(self) -> CGStats:
        """Return and reset the statistics of the solves so far (one host synchronisation).

        Raises:
            RuntimeError: A grid barrier of the "grid" mode timed out (its blocks were not all resident), so
                the solves since the last call are not to be trusted.
        """
        if int(self.stalled.numpy()[0]):
            self.stalled.zero_()
            raise RuntimeError(
                f"CG grid barrier timed out ({self.grid_blocks} blocks not all resident): use mode='launches'"
            )
        solves, iterations, short = (int(c) for c in self.counts.numpy())
        stats = CGStats(solves, iterations, float(self.residual_max.numpy()[0]), short)
        self.counts.zero_()
        self.residual_max.zero_()
        return stats

"""Block-Jacobi preconditioned conjugate gradients on the device, capturable as one CUDA graph.

The iteration runs under ``wp.capture_while`` on a device-side condition, so the same code gives a fixed
iteration count (tolerance 0) or iteration to a tolerance, with no host synchronisation on CUDA. The
tolerance and the iteration count live in device arrays: changing them needs no new graph capture.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import warp as wp

from warpfem.kernels import cg as K

BLOCK = 256
"""Threads per block of the kernels that reduce dot products."""


@dataclass(frozen=True)
class CGStats:
    """What the solves since the last :meth:`CGSolver.read_stats` did.

    Attributes:
        solves: Number of solves.
        iterations: Total iterations over those solves.
        residual_max: Largest final relative residual sqrt(r.M^-1 r / b.M^-1 b).
    """

    solves: int
    iterations: int
    residual_max: float


class CGSolver:
    """Solves A x = b for a 3x3-block CSR matrix with a fixed structure.

    Args:
        row_start: (n+1) int32 row offsets.
        cols: (nnz) int32 block columns.
        free: (n) int32, 0 for rows held at their initial value.
        max_iterations: Capacity: the most iterations any solve may be asked for.
        device: Warp device.
    """

    def __init__(self, row_start: wp.array, cols: wp.array, free: wp.array, max_iterations: int, device) -> None:
        self.device = wp.get_device(device)
        self.row_start, self.cols, self.free = row_start, cols, free
        n = free.shape[0]
        self.padded = -(-n // BLOCK) * BLOCK  # whole blocks for the tile reductions
        self.capacity = int(max_iterations)
        self.r = wp.zeros(n, dtype=wp.vec3, device=self.device)
        self.z = wp.zeros_like(self.r)
        self.p = wp.zeros_like(self.r)
        self.q = wp.zeros_like(self.r)
        self.extra_q = wp.zeros_like(self.r)
        self.rz = wp.zeros(self.capacity + 2, dtype=float, device=self.device)
        self.pq = wp.zeros(self.capacity + 1, dtype=float, device=self.device)
        self.bz = wp.zeros(1, dtype=float, device=self.device)
        self.iteration = wp.zeros(1, dtype=wp.int32, device=self.device)
        self.cond = wp.zeros(1, dtype=wp.int32, device=self.device)
        self.tolerance = wp.zeros(1, dtype=float, device=self.device)
        self.max_iterations = wp.zeros(1, dtype=wp.int32, device=self.device)
        self.counts = wp.zeros(2, dtype=wp.int32, device=self.device)  # solves, iterations
        self.residual_max = wp.zeros(1, dtype=float, device=self.device)
        self.configure(max_iterations, 0.0)

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

    def solve(
        self,
        values: wp.array,
        diag_inv: wp.array,
        b: wp.array,
        x: wp.array,
        extra: Callable[[wp.array, wp.array], None] | None = None,
    ) -> None:
        """Solve ``A x = b`` starting from the ``x`` given; ``diag_inv`` holds the inverse diagonal blocks.

        ``extra(p, q_out)``, if given, launches kernels writing a matrix-free part of ``A p`` (for example the
        contacts) into ``q_out``; it is added to the assembled product everywhere A is applied.
        """
        n = self.free.shape[0]
        dev = self.device
        self.rz.zero_()
        self.pq.zero_()
        self.bz.zero_()
        structure = [self.row_start, self.cols, values]
        has_extra = int(extra is not None)
        if extra is not None:
            extra(x, self.extra_q)
        rows = self.padded
        wp.launch(
            K.cg_init,
            dim=rows,
            block_dim=BLOCK,
            inputs=[n, *structure, diag_inv, self.free, b, x, self.extra_q, has_extra],
            outputs=[self.r, self.z, self.p, self.rz, self.bz],
            device=dev,
        )
        limits = [self.tolerance, self.max_iterations]
        wp.launch(
            K.cg_start,
            dim=1,
            inputs=[self.rz, self.bz, *limits],
            outputs=[self.iteration, self.cond],
            device=dev,
        )

        def iterate() -> None:
            if extra is not None:
                extra(self.p, self.extra_q)
            wp.launch(
                K.cg_spmv,
                dim=rows,
                block_dim=BLOCK,
                inputs=[n, *structure, self.free, self.p, self.iteration, self.extra_q, has_extra],
                outputs=[self.q, self.pq],
                device=dev,
            )
            wp.launch(
                K.cg_update_xr,
                dim=rows,
                block_dim=BLOCK,
                inputs=[n, diag_inv, self.p, self.q, self.iteration, self.pq, self.rz],
                outputs=[x, self.r, self.z, self.rz],
                device=dev,
            )
            wp.launch(K.cg_update_p, dim=n, inputs=[self.z, self.iteration, self.rz], outputs=[self.p], device=dev)
            wp.launch(
                K.cg_advance,
                dim=1,
                inputs=[self.rz, self.pq, self.bz, *limits],
                outputs=[self.iteration, self.cond],
                device=dev,
            )

        wp.capture_while(self.cond, iterate)
        wp.launch(
            K.cg_finish,
            dim=1,
            inputs=[self.rz, self.bz, self.iteration],
            outputs=[self.counts, self.residual_max],
            device=dev,
        )

    def read_stats(self) -> CGStats:
        """Return and reset the statistics of the solves so far (one host synchronisation)."""
        solves, iterations = (int(c) for c in self.counts.numpy())
        stats = CGStats(solves, iterations, float(self.residual_max.numpy()[0]))
        self.counts.zero_()
        self.residual_max.zero_()
        return stats

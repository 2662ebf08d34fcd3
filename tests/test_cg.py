"""The fused block-Jacobi PCG against NumPy's dense solver."""

import numpy as np
import pytest
import warp as wp

from warpfem.cg import CGSolver
from warpfem.model import block_pattern
from warpfem.shapes import box_tet_mesh


def _system(device, seed=0, pinned=()):
    """A random SPD 3x3-block system on a tet mesh's sparsity pattern; returns solver inputs and dense A."""
    rng = np.random.default_rng(seed)
    V, T = box_tet_mesh((0, 0, 0), (1, 1, 1), (2, 2, 2))
    n = len(V)
    row_start, cols, diag_slot, tet_slots = block_pattern(T, n)
    A = np.zeros((3 * n, 3 * n))
    for t in T:  # each tet adds a random SPD 12x12 coupling its corners
        B = rng.normal(size=(12, 12))
        idx = np.concatenate([np.arange(3 * v, 3 * v + 3) for v in t])
        A[np.ix_(idx, idx)] += B @ B.T
    A += 0.5 * np.eye(3 * n)
    values = np.stack(
        [A[3 * i : 3 * i + 3, 3 * c : 3 * c + 3] for i in range(n) for c in cols[row_start[i] : row_start[i + 1]]]
    )
    free = np.ones(n, np.int32)
    free[list(pinned)] = 0
    diag_inv = np.stack([np.linalg.inv(A[3 * i : 3 * i + 3, 3 * i : 3 * i + 3]) for i in range(n)])
    diag_inv[free == 0] = 0
    arrays = dict(
        row_start=wp.array(row_start, dtype=wp.int32, device=device),
        cols=wp.array(cols, dtype=wp.int32, device=device),
        free=wp.array(free, dtype=wp.int32, device=device),
        values=wp.array(values.astype(np.float32), dtype=wp.mat33, device=device),
        diag_inv=wp.array(diag_inv.astype(np.float32), dtype=wp.mat33, device=device),
    )
    return arrays, A, free, rng


def test_cg_solves_spd_system_to_tolerance(device):
    a, A, _, rng = _system(device)
    n = A.shape[0] // 3
    b = rng.normal(size=(n, 3))
    cg = CGSolver(a["row_start"], a["cols"], a["free"], 500, device)
    cg.configure(500, 1e-6)
    x = wp.zeros(n, dtype=wp.vec3, device=device)
    cg.solve(a["values"], a["diag_inv"], wp.array(b.astype(np.float32), dtype=wp.vec3, device=device), x)
    stats = cg.read_stats()
    reference = np.linalg.solve(A, b.ravel())
    assert stats.solves == 1 and 0 < stats.iterations < 500
    assert stats.residual_max <= 1e-6
    np.testing.assert_allclose(x.numpy().ravel(), reference, atol=1e-4 * np.abs(reference).max())
    assert np.linalg.norm(A @ x.numpy().ravel() - b.ravel()) < 1e-4 * np.linalg.norm(b)


def test_fixed_iteration_count_is_exact(device):
    a, A, _, rng = _system(device, seed=1)
    n = A.shape[0] // 3
    b = wp.array(rng.normal(size=(n, 3)).astype(np.float32), dtype=wp.vec3, device=device)
    cg = CGSolver(a["row_start"], a["cols"], a["free"], 50, device)
    residuals = []
    for iters in (3, 7):
        cg.configure(iters, 0.0)
        cg.solve(a["values"], a["diag_inv"], b, wp.zeros(n, dtype=wp.vec3, device=device))
        stats = cg.read_stats()
        assert stats.iterations == iters
        residuals.append(stats.residual_max)
    assert residuals[1] < residuals[0]


def test_pinned_rows_keep_their_start_value(device):
    pinned = (0, 5, 11)
    a, A, free, rng = _system(device, seed=2, pinned=pinned)
    n = A.shape[0] // 3
    b = rng.normal(size=(n, 3))
    b[list(pinned)] = 0.0
    cg = CGSolver(a["row_start"], a["cols"], a["free"], 500, device)
    cg.configure(500, 1e-7)
    x = wp.zeros(n, dtype=wp.vec3, device=device)
    cg.solve(a["values"], a["diag_inv"], wp.array(b.astype(np.float32), dtype=wp.vec3, device=device), x)
    dofs = np.repeat(free == 1, 3)
    reference = np.zeros(3 * n)
    reference[dofs] = np.linalg.solve(A[np.ix_(dofs, dofs)], b.ravel()[dofs])
    np.testing.assert_allclose(x.numpy().ravel(), reference, atol=1e-4 * np.abs(reference).max())
    assert np.all(x.numpy()[list(pinned)] == 0.0)


def test_configure_rejects_out_of_range(device):
    a, _, _, _ = _system(device)
    cg = CGSolver(a["row_start"], a["cols"], a["free"], 10, device)
    with pytest.raises(ValueError):
        cg.configure(11, 1e-3)
    with pytest.raises(ValueError):
        cg.configure(5, 1.5)

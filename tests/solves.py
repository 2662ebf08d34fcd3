"""Every linear system a run's steps solve, kept and checked with SciPy: the matrix rebuilt from the solver's
stored blocks and contact pairs, and the residual of CG's answer measured there, independently of CG's own
figure."""

import numpy as np
import scipy.sparse as sp


def system(model, values, pairs):
    """The solve's matrix with SciPy: stored upper-triangle blocks mirrored, plus each contact pair's coupling
    between distinct nodes (``J^T C J`` off the diagonal; the diagonal blocks already hold ``w^2 C``)."""
    n = model.vertex_count
    starts, cols = model.row_start.numpy(), model.cols.numpy()
    rows = np.repeat(np.arange(n), np.diff(starts))
    a, b = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")
    r = (3 * rows[:, None, None] + a).ravel()
    c = (3 * cols[:, None, None] + b).ravel()
    upper = sp.coo_matrix((values.reshape(-1), (r, c)), shape=(3 * n, 3 * n)).tocsr()
    strict = upper - sp.block_diag([values[s] for s in model.diag_slot.numpy()]).tocsr()
    A = upper + strict.T
    va, wa, vb, wb, C = pairs
    if len(va):
        idx = np.concatenate([va, vb], axis=1)  # (k, 8) nodes
        w = np.concatenate([wa, -wb], axis=1)  # (k, 8) weights
        p, q = np.meshgrid(np.arange(8), np.arange(8), indexing="ij")
        keep = p != q
        p, q = p[keep], q[keep]
        blk = (w[:, p] * w[:, q])[:, :, None, None] * C[:, None]  # (k, 56, 3, 3)
        r = (3 * idx[:, p][:, :, None, None] + a).ravel()
        c = (3 * idx[:, q][:, :, None, None] + b).ravel()
        A = A + sp.coo_matrix((blk.ravel(), (r, c)), shape=A.shape).tocsr()
    return A.tocsr()


def record_solves(sim):
    """Wrap the solver's CG (on the CPU, not captured) so that every solve keeps its inputs, its start
    (``x0``) and its answer (``x``)."""
    cg, solves = sim.solver.cg, []
    solve = cg.solve

    def recording(values, diag_inv, b, x, *args, **kwargs):
        pairs = [np.zeros((0, 4), int), np.zeros((0, 4)), np.zeros((0, 4), int), np.zeros((0, 4)), np.zeros((0, 3, 3))]
        if sim.solver.collider is not None:
            c = sim.solver.collider.coupling
            k = int(c.count.numpy()[0])
            pairs = [arr.numpy()[:k].copy() for arr in (c.verts_a, c.weights_a, c.verts_b, c.weights_b, c.matrix)]
        entry = dict(values=values.numpy().copy(), b=b.numpy().copy(), x0=x.numpy().copy(), pairs=pairs)
        out = solve(values, diag_inv, b, x, *args, **kwargs)
        entry["x"] = x.numpy().copy()
        solves.append(entry)
        return out

    cg.solve = recording
    return solves


def worst_residual(sim, solves) -> float:
    """The largest relative residual of the kept solves on the free rows, in the block-Jacobi norm of CG's
    stopping rule (``sqrt(r.M^-1 r / b.M^-1 b)``, M the 3x3 diagonal blocks), computed in float64."""
    free = np.repeat(sim.model.free.numpy() != 0, 3)
    worst = 0.0
    for s in solves:
        A = system(sim.model, s["values"], s["pairs"])[free][:, free]
        b, x = s["b"].reshape(-1)[free].astype(float), s["x"].reshape(-1)[free].astype(float)
        blocks = [A[i : i + 3, i : i + 3].toarray() for i in range(0, A.shape[0], 3)]
        m_inv = sp.block_diag([np.linalg.inv(blk) for blk in blocks]).tocsr()
        r = b - A @ x
        worst = max(worst, float(np.sqrt((r @ (m_inv @ r)) / (b @ (m_inv @ b)))))
    return worst

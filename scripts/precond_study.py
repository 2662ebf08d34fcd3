"""Which preconditioner keeps a stiff body resting on a soft one converging?

Runs a stack of bunnies (Young's moduli from the command line, bottom first) to a frame on the CPU, takes the
next step's first system (assembled blocks plus the contact pairs' coupling), and counts SciPy PCG iterations
to a relative residual of 1e-4 from the solver's start with block Jacobi, and with block Jacobi plus an
additive coarse correction on per-body translations, rigid modes or affine modes.

    python scripts/precond_study.py 3e5,1e7 30
"""

import sys

import numpy as np
import scipy.sparse as sp
import warp as wp

import warpfem

wp.config.quiet = True


def scene(youngs, frames=60):
    """A stack of 0.5-scale bunnies, one per Young's modulus (Pa), bottom first."""
    objs = []
    for k, y in enumerate(youngs):
        objs.append(
            {
                "name": f"b{k}",
                "mesh": "builtin:bunny",
                "subdivide": 0,
                "faces": 400,
                "scale": 0.5,
                "translate": [0.05 * k, 0.25 + 0.42 * k, 0.0],
                "young": y,
            }
        )
    return warpfem.Scene.from_dict({"scene": {"frames": frames, "substeps": 4}, "object": objs}, name="contrast")


youngs = [float(y) for y in sys.argv[1].split(",")]
frame = int(sys.argv[2])
sim = warpfem.Simulation(scene(youngs), device="cpu")
for _ in range(frame):
    sim.step_frame()
snap = {}
cg = sim.solver.cg
orig = cg.solve


def grab(values, diag_inv, b, x, direction=None, mass=None):
    if not snap:
        snap.update(values=values.numpy().copy(), b=b.numpy().copy(), x=x.numpy().copy())
        c = sim.solver.collider.coupling
        k = int(c.count.numpy()[0])
        snap["pairs"] = [a.numpy()[:k].copy() for a in (c.verts_a, c.weights_a, c.verts_b, c.weights_b, c.matrix)]
    return orig(values, diag_inv, b, x, direction, mass)


cg.solve = grab
sim.step_frame()
m = sim.model
n = m.vertex_count
rs, cols, free, body = (a.numpy() for a in (m.row_start, m.cols, m.free, m.vertex_body))
rows = np.repeat(np.arange(n), np.diff(rs))
V = snap["values"]
rows_u, cols_u, data_u = [], [], []
for a in range(3):
    for b in range(3):
        rows_u.append(3 * rows + a)
        cols_u.append(3 * cols + b)
        data_u.append(V[:, a, b])
U = sp.coo_matrix((np.concatenate(data_u), (np.concatenate(rows_u), np.concatenate(cols_u))), shape=(3 * n, 3 * n))
U = U.tocsr()
# the upper triangle's blocks mirrored; the diagonal blocks are stored whole
dblocks = sp.block_diag([V[s] for s in m.diag_slot.numpy()]).tocsr()
A = (U - dblocks) + (U - dblocks).T + dblocks
va, wa, vb, wb, C = snap["pairs"]
rows_c, cols_c, dat = [], [], []
for c in range(len(va)):
    idx = np.concatenate([va[c], vb[c]])
    w = np.concatenate([wa[c], -wb[c]])
    for p in range(8):
        for q in range(8):
            if p == q:
                continue  # the assembled matrix already holds w^2 C
            blk = w[p] * w[q] * C[c]
            for a in range(3):
                for b in range(3):
                    rows_c.append(3 * idx[p] + a)
                    cols_c.append(3 * idx[q] + b)
                    dat.append(blk[a, b])
A = A + sp.coo_matrix((dat, (rows_c, cols_c)), shape=A.shape).tocsr()
keep = np.repeat(free != 0, 3)
A = A[keep][:, keep]
b = snap["b"].reshape(-1)[keep]
x0 = snap["x"].reshape(-1)[keep]
bf = body[free != 0]
xf = sim.states[0].x.numpy()[free != 0].astype(float)
print(f"bodies {youngs} frame {frame}: n {A.shape[0] // 3} pairs {len(va)}; symmetric {abs(A - A.T).max():.2g}")

nb = A.shape[0] // 3
blocks = [A[3 * i : 3 * i + 3, 3 * i : 3 * i + 3].toarray() for i in range(nb)]
Dinv = sp.block_diag([np.linalg.inv(B) for B in blocks]).tocsr()


def coarse(rot):
    cols_ = []
    for bd in np.unique(bf):
        sel = bf == bd
        c = xf[sel].mean(0)
        for a in range(3):
            z = np.zeros((nb, 3))
            z[sel, a] = 1.0
            cols_.append(z.reshape(-1))
        if rot == "affine":
            r = xf - c
            for a in range(3):
                for k in range(3):
                    z = np.zeros((nb, 3))
                    z[sel, a] = r[sel, k]
                    cols_.append(z.reshape(-1))
        elif rot:
            r = xf - c
            for a in range(3):
                e = np.zeros(3)
                e[a] = 1.0
                z = np.zeros((nb, 3))
                z[sel] = np.cross(e, r[sel])
                cols_.append(z.reshape(-1))
    Z = np.stack(cols_, 1)
    E = Z.T @ (A @ Z)
    Einv = np.linalg.inv(E)
    return lambda r: Dinv @ r + Z @ (Einv @ (Z.T @ r))


def pcg(apply, tol=1e-4, cap=2000):
    x = x0.copy()
    r = b - A @ x
    z = apply(r)
    p = z.copy()
    rz = r @ z
    bz = b @ apply(b)
    for k in range(cap):
        if np.sqrt(max(rz, 0) / bz) < tol:
            return k
        Ap = A @ p
        al = rz / (p @ Ap)
        x += al * p
        r -= al * Ap
        z = apply(r)
        rz2 = r @ z
        p = z + rz2 / rz * p
        rz = rz2
    return cap


print("block Jacobi", pcg(lambda r: Dinv @ r))
print("+ per-body translations (3 per body)", pcg(coarse(False)))
print("+ per-body rigid modes (6 per body)", pcg(coarse(True)))
print("+ per-body affine modes (12 per body)", pcg(coarse("affine")))

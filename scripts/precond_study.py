"""Which preconditioner or start keeps CG converging where bodies are stiff, or differ in stiffness?

Runs a scene to a frame on the CPU, records the next frame's linear systems (the stored blocks plus the contact
pairs' coupling, rebuilt with SciPy) and counts PCG iterations to a relative residual of 1e-4 (block-Jacobi
norm, CG's own stopping rule) with block Jacobi from the solver's start and from zero, from the start corrected
along each body's affine modes (one Galerkin solve of 12 unknowns a body before CG), and with an additive
coarse correction on per-body translations, rigid or affine modes in every iteration.

    python scripts/precond_study.py 1e7,3e5 30                        # a stack of bunnies, bottom first
    python scripts/precond_study.py 1e7 30 --mesh ../shared/assets/horse.ply --size 1.5   # one body alone

The stack is half-size bunnies of 400 faces; ``--mesh`` drops one body of that mesh (500 coarse faces, as the
bench's mixed pile builds it) and sizes it to ``--size`` m. Also prints, per body, the largest and median ratio
of a vertex's diagonal block to its mass (the Jacobi-scaled system's condition is about their largest).
"""

import argparse
import sys
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import warp as wp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))
sys.path.insert(0, str(ROOT / "tests"))

from solves import record_solves, system  # noqa: E402
from test_friction import _bunny_stack  # noqa: E402

import warpfem  # noqa: E402

wp.config.quiet = True


def single(mesh: str, size: float, young: float) -> warpfem.Scene:
    """One body of ``mesh`` (500 faces), ``size`` m across, dropped on the ground as the bench's mixed pile does."""
    from bench import mixed_pile

    base = warpfem.load_scene(ROOT / "scenes" / "default.toml")
    return mixed_pile(base, [(str(Path(mesh).resolve()), 500)], copies=1, sizes=(size, size), youngs=(young, young))


def affine_modes(x: np.ndarray, body: np.ndarray, rotations_only: bool | str) -> np.ndarray:
    """Columns spanning each body's translations (False), rigid modes (True) or affine modes ("affine")."""
    cols, n = [], len(x)
    for b in np.unique(body):
        sel = body == b
        r = x - x[sel].mean(0)
        for a in range(3):
            z = np.zeros((n, 3))
            z[sel, a] = 1.0
            cols.append(z.reshape(-1))
            if rotations_only == "affine":
                for k in range(3):
                    z = np.zeros((n, 3))
                    z[sel, a] = r[sel, k]
                    cols.append(z.reshape(-1))
            elif rotations_only:
                z = np.zeros((n, 3))
                z[sel] = np.cross(np.eye(3)[a], r[sel])
                cols.append(z.reshape(-1))
    return np.stack(cols, 1)


def pcg(A, b, x, apply, m_inv, tol=1e-4, cap=3000) -> int:
    """Iterations of PCG (preconditioner ``apply``) from ``x`` to ``tol`` in the block-Jacobi norm."""
    x = x.copy()
    r = b - A @ x
    z = apply(r)
    p, rz, bz = z.copy(), r @ z, b @ (m_inv @ b)
    for k in range(cap):
        if np.sqrt(max(r @ (m_inv @ r), 0.0) / bz) < tol:
            return k
        q = A @ p
        alpha = rz / (p @ q)
        x += alpha * p
        r -= alpha * q
        z = apply(r)
        rz, beta = r @ z, (r @ z) / rz
        p = z + beta * p
    return cap


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("youngs", help="comma list of Young's moduli (Pa): the stack, bottom first, or one body")
    parser.add_argument("frame", type=int, help="frames run before the systems are recorded")
    parser.add_argument("--mesh", help="one body of this mesh instead of the bunny stack")
    parser.add_argument("--size", type=float, default=1.5, help="m: the body's bounding-box diagonal (--mesh)")
    parser.add_argument("--solves", type=int, default=3, help="how many of the next frame's solves to study")
    args = parser.parse_args()
    youngs = [float(y) for y in args.youngs.split(",")]
    scene = single(args.mesh, args.size, youngs[0]) if args.mesh else _bunny_stack(youngs)
    sim = warpfem.Simulation(scene, device="cpu")
    for _ in range(args.frame):
        sim.step_frame()
    solves = record_solves(sim)
    sim.step_frame()
    model = sim.model
    free_v = model.free.numpy() != 0
    free = np.repeat(free_v, 3)
    body = model.vertex_body.numpy()[free_v]
    x = sim.states[0].x.numpy()[free_v].astype(float)
    mass = model.mass.numpy()[free_v]
    what = args.mesh or "bunny stack"
    print(f"{what} {youngs} frame {args.frame}: {int(free_v.sum())} free vertices, {len(solves)} solves")
    for s in solves[: args.solves]:
        A = system(model, s["values"], s["pairs"])[free][:, free].tocsr()
        print(f"  {len(s['pairs'][0])} contact pairs")
        study(A, s["b"].reshape(-1)[free].astype(float), s["x0"].reshape(-1)[free].astype(float), x, body, mass)


def study(A, b: np.ndarray, x0: np.ndarray, x: np.ndarray, body: np.ndarray, mass: np.ndarray) -> None:
    """Print one system's diagonal-to-mass ratios and the iterations each preconditioner or start needs."""
    blocks = [A[i : i + 3, i : i + 3].toarray() for i in range(0, A.shape[0], 3)]
    m_inv = sp.block_diag([np.linalg.inv(blk) for blk in blocks]).tocsr()
    ratio = np.array([np.trace(blk) / 3.0 for blk in blocks]) / mass
    per_body = ", ".join(
        f"{int(bd)}: {ratio[body == bd].max():.0f} / {np.median(ratio[body == bd]):.0f}" for bd in np.unique(body)
    )
    print(f"    diagonal / mass, largest / median per body: {per_body}")

    def jacobi(r):
        return m_inv @ r

    def coarse(kind):
        P = affine_modes(x, body, kind)
        e_inv = np.linalg.pinv(P.T @ (A @ P))
        return P, e_inv, lambda r: m_inv @ r + P @ (e_inv @ (P.T @ r))

    P, e_inv, additive = coarse("affine")
    corrected = x0 + P @ (e_inv @ (P.T @ (b - A @ x0)))
    print(
        f"    block Jacobi: from the solver's start {pcg(A, b, x0, jacobi, m_inv)}, from zero "
        f"{pcg(A, b, 0 * x0, jacobi, m_inv)}, from the affine-corrected start {pcg(A, b, corrected, jacobi, m_inv)}"
    )
    print(
        "    additive coarse correction every iteration (from the solver's start): translations "
        f"{pcg(A, b, x0, coarse(False)[2], m_inv)}, rigid {pcg(A, b, x0, coarse(True)[2], m_inv)}, "
        f"affine {pcg(A, b, x0, additive, m_inv)}"
    )


if __name__ == "__main__":
    main()

"""Kinematic handles against stiff implicit springs: how closely held vertices follow, and what CG pays.

    .venv/bin/python scripts/handle_trial.py [--device cpu]

A 0.2 x 0.2 x 0.1 m block (E 1e6 Pa) hangs from its top face, which the keys shake 5 cm and turn 30 degrees
in 0.1 s; 24 frames at 60 fps, 3 substeps. Kinematic: the solver's handles (held vertices leave the solve
with the velocity that lands them on the pose). Spring: the same vertices left free, each pulled to its pose
at the step's end by an implicit spring of stiffness k per unit mass (``dt^2 k m`` on its diagonal block,
``dt k m (target - x)`` on its right-hand side), the target uploaded each step. Prints the largest distance
of a held vertex from its pose over the run (% of the block's size) and the mean CG iterations per step.
"""

import argparse

import numpy as np
import warp as wp

import warpfem
from warpfem.build import keyed_motion
from warpfem.prep.shapes import box_tet_mesh
from warpfem.sim import integrate
from warpfem.sim.drive import Handle
from warpfem.sim.solver import Solver

KEYS = [[0.0, 0, 0, 0, 0, 0, 0], [0.1, 0.05, 0.02, 0, 10, 30, 0], [0.25, -0.05, 0, 0.03, -20, -30, 15]]


@wp.kernel
def spring(
    held: wp.array(dtype=wp.int32),
    target: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    diag_slot: wp.array(dtype=wp.int32),
    k: float,
    dt: float,
    matrix: wp.array(dtype=wp.mat33),
    rhs: wp.array(dtype=wp.vec3),
    diag_inv: wp.array(dtype=wp.mat33),
):
    j = wp.tid()
    i = held[j]
    km = k * mass[i]
    block = matrix[diag_slot[i]] + dt * dt * km * wp.identity(n=3, dtype=float)
    matrix[diag_slot[i]] = block
    rhs[i] = rhs[i] + dt * km * (target[j] - x[i])
    diag_inv[i] = wp.inverse(block)


def run(device: str, k: float | None) -> tuple[float, float]:
    v, t = box_tet_mesh((0, 0.3, 0), (0.2, 0.5, 0.1), (4, 4, 2))
    top = v[:, 1] > 0.5 - 1e-9
    held = np.flatnonzero(top)
    motion = keyed_motion(KEYS, (0.1, 0.5, 0.05))
    builder = warpfem.ModelBuilder()
    warpfem.add_body(builder, "block", v, t, 1e6, 0.3, 1000.0, pinned=top if k is None else None)
    model = builder.finalize(device)
    solver = Solver(model, handles=[Handle(held, motion)] if k is None else [], cg_iterations=200)
    substeps, dt = 3, 1 / 180
    target = wp.zeros(len(held), dtype=wp.vec3, device=device)
    held_dev = wp.array(held.astype(np.int32), dtype=wp.int32, device=device)
    states = [model.state(), model.state()]
    worst, build = 0.0, integrate.build_system
    for step in range(24 * substeps):
        r, move = motion.at((step + 1) * dt)
        target.assign((v[held] @ r.T + move).astype(np.float32))
        if k is not None:

            def with_spring(m, state, *args, **kwargs):
                build(m, state, *args, **kwargs)
                wp.launch(spring, dim=len(held), inputs=[held_dev, target, state.x, m.mass, m.diag_slot, k, dt],
                          outputs=[solver.matrix, solver.rhs, solver.diag_inv], device=device)  # fmt: skip

            integrate.build_system = with_spring
        solver.step(states[0], states[1], dt)
        integrate.build_system = build
        states.reverse()
        worst = max(worst, float(np.abs(states[0].x.numpy()[held] - target.numpy()).max()))
    stats = solver.read_cg_stats()
    size = float(np.linalg.norm(np.ptp(v, axis=0)))
    return 100 * worst / size, stats.iterations / max(stats.solves, 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    wp.config.quiet = True
    for k in (None, 1e5, 1e6, 1e7, 1e8):
        error, iterations = run(args.device, k)
        label = "kinematic" if k is None else f"spring k {k:.0e} 1/s^2"
        print(f"{label:24s} held vertices off their pose by at most {error:.2g} % of the size; CG {iterations:.1f}")


if __name__ == "__main__":
    main()

"""How far float32 lets CG go on a stiff body: the system's residual against what CG reports and the run's estimate.

Drops one body on the ground for ``--frames`` frames on the CPU, keeps every solve, and rebuilds each system
with SciPy from the solver's stored blocks (``tests/solves.py``): prints, per Young's modulus, the largest ratio
R of a free vertex's diagonal block to its mass, u R (u = 2^-24), the run's floor estimate, the worst residual
CG reported, the worst residual of its float32 answers measured in float64, and the solves stopped at the cap.
The figures of docs/decisions.md, "CG's float32 floor, said" and "CG's cap 400 by default".

    python scripts/float32_floor.py 1e7,1e8,3e8,1e9,3e9              # the bunny of 400 faces as loaded, 2.6 m
    python scripts/float32_floor.py 1e8,1e9 --size 1.2977 --drop 0.15  # the same scaled by half
    python scripts/float32_floor.py 1e8 --substeps 1
    python scripts/float32_floor.py 1e8 --elements quadratic
    python scripts/float32_floor.py 1e8,1e9 --size 1.0                 # sized to 1 m
    python scripts/float32_floor.py 3e6,1e7 --mesh ../shared/assets/horse.ply --faces 500 --size 0.38
    python scripts/float32_floor.py 1e7,1e8 --mesh ../shared/assets/horse.ply --faces 500 --size 1.5
    python scripts/float32_floor.py 1e8 --cap 100                      # the cap before 400: solves stopped short
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import warp as wp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from solves import record_solves, worst_residual  # noqa: E402

import warpfem  # noqa: E402
from warpfem.simulation import diagonal_to_mass  # noqa: E402

wp.config.quiet = True
U = 2.0**-24


def scene(args: argparse.Namespace, young: float) -> warpfem.Scene:
    """One body of ``args.mesh`` rotated a little, its bounding-box diagonal ``args.size`` m, its centre ``args.drop``
    m above the ground."""
    mesh = args.mesh if args.mesh == "builtin:bunny" else str(Path(args.mesh).resolve())
    probe = warpfem.prepare(mesh, faces=args.faces)
    scale = args.size / float(np.linalg.norm(np.ptp(probe.dense_vertices, axis=0))) if args.size else 1.0
    body = {"name": "b", "mesh": mesh, "subdivide": 0, "faces": args.faces, "rotate": [15.0, 30.0, 0.0]}
    body.update(scale=scale, translate=[0.0, args.drop, 0.0], young=young)
    solver = {"elements": args.elements, **({"cg_iterations": args.cap} if args.cap else {})}
    doc = {"scene": {"frames": args.frames, "substeps": args.substeps}, "solver": solver, "object": [body]}
    return warpfem.Scene.from_dict(doc, name="floor")


def ratio(sim: warpfem.Simulation, solves: list[dict]) -> float:
    """The largest ratio of a free vertex's diagonal block (2-norm) to its mass over the last few solves."""
    mass, slots, free = sim.model.mass.numpy(), sim.model.diag_slot.numpy(), sim.model.free.numpy() != 0
    return max(float(diagonal_to_mass(s["values"][slots], mass, free).max()) for s in solves[-5:])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("youngs", help="comma list of Young's moduli (Pa)")
    parser.add_argument("--mesh", default="builtin:bunny")
    parser.add_argument("--size", type=float, default=0.0, help="m: the body's bounding-box diagonal (0: as loaded)")
    parser.add_argument("--drop", type=float, default=0.3, help="m: the height of the body's placement")
    parser.add_argument("--faces", type=int, default=400)
    parser.add_argument("--substeps", type=int, default=4)
    parser.add_argument("--elements", choices=("linear", "quadratic"), default="linear")
    parser.add_argument("--cap", type=int, default=0, help="CG's cap (0: the scene default)")
    parser.add_argument("--frames", type=int, default=30)
    args = parser.parse_args(argv)
    for young in (float(y) for y in args.youngs.split(",")):
        sim = warpfem.Simulation(scene(args, young), device="cpu")
        solves = record_solves(sim)
        for _ in range(args.frames):
            sim.step_frame()
        t, r = sim.totals, ratio(sim, solves)
        print(
            f"E {young:.0e} Pa: R {r:.3g}, u R {U * r:.2e}, estimate {t.cg_float32_floor:.2e}; residual reported "
            f"{t.cg_residual_max:.2e}, measured {worst_residual(sim, solves):.2e}; {t.cg_short_solves} of "
            f"{t.cg_solves} solves short, {t.cg_iterations / t.cg_solves:.1f} iterations a solve",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())

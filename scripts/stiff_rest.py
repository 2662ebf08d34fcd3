"""Does a very stiff body come to rest on the ground? (docs/decisions.md, "Static contacts from an offset").

    .venv/bin/python scripts/stiff_rest.py --device cuda:0 --offset 0 --runs 8
    .venv/bin/python scripts/stiff_rest.py --device cuda:0 --offset 0.0008 --runs 8

The default scene's bunny made 1 GPa, nu 0.49, at 24 steps a second (`tests/test_stability.py`'s stiff body),
dropped for 2 s onto a ground with the given offset: per run, its lowest dense point from 1 s on (% of its
size, the ground at 0) and how far it moved in its last frame (% of its size), and the frames CG ended at its
cap. On CUDA runs differ (float atomics add in another order), so several runs show the spread.
"""

from __future__ import annotations

import argparse

import numpy as np


def one_run(device: str, offset: float) -> str:
    """One 2 s drop; its line of figures."""
    import warpfem

    body = {"name": "bunny", "mesh": "builtin:bunny", "subdivide": 0, "faces": 400, "scale": 0.5}
    body.update(rotate=[15.0, 30.0, 0.0], translate=[0.0, 1.0, 0.0], young=1e9, poisson=0.49, damping_stiffness=0.005)
    doc = {"scene": {"frames": 48, "fps": 24.0, "substeps": 1}, "ground": {"offset": offset}, "object": [body]}
    sim = warpfem.Simulation(warpfem.Scene.from_dict(doc, name="stiff"), device=device)
    size = float(np.linalg.norm(np.ptp(sim.dense_points("bunny"), axis=0)))
    lowest, previous = [], None
    for frame in range(48):
        sim.step_frame()
        points = sim.dense_points("bunny")
        if frame >= 24:
            lowest.append(float(points[:, 1].min()))
        if frame == 46:
            previous = points
    moved = float(np.abs(points - previous).max())
    return (
        f"offset {offset}: lowest {100 * min(lowest) / size:+.3f} .. {100 * max(lowest) / size:+.3f} %, "
        f"moved {100 * moved / size:.4f} % in the last frame, CG at its cap in {sim.totals.cg_capped_frames} frames"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--offset", type=float, default=0.0008, help="the ground's offset (share of the size)")
    parser.add_argument("--runs", type=int, default=1)
    args = parser.parse_args()
    for _ in range(args.runs):
        print(one_run(args.device, args.offset))


if __name__ == "__main__":
    main()

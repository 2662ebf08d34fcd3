"""Does a very stiff body come to rest on the ground? (docs/decisions.md, "Resting contacts under gravity").

    .venv/bin/python scripts/stiff_rest.py --device cuda:0 --runs 3
    .venv/bin/python scripts/stiff_rest.py --device cuda:0 --offset 0 --young 1e9 --substeps 1 --runs 8

The drop of `tests/test_stability.py`'s stiff-body test, through the public API only (so it also runs where
preprocessing cannot, from a filled cache): the default scene's bunny at ``--young`` Pa (default: 1e9 and
1e8), nu 0.49, 24 frames a second of ``--substeps`` steps (default: 1 and 2), dropped for 2 s onto the
ground (``--offset``: its offset, share of the size; default: the scene's). Per run: its lowest dense point
from 1 s on (% of its size, the ground at 0), how far it moved in its last frame, and whether both are within
the test's 0.1 %. On CUDA runs differ (float atomics add in another order), so several runs show the spread.
"""

from __future__ import annotations

import argparse

import numpy as np


def stiff_drop(
    device: str, young: float = 1e9, substeps: int = 1, offset: float | None = None
) -> tuple[float, list[float], float]:
    """One 2 s drop: the body's size, its lowest dense point each frame from 1 s on, and how far it moved in its
    last frame (m). `tests/test_stability.py`'s stiff-body test runs this drop."""
    import warpfem

    body = {
        "name": "bunny",
        "mesh": "builtin:bunny",
        "subdivide": 0,
        "faces": 400,
        "scale": 0.5,
        "rotate": [15.0, 30.0, 0.0],
        "translate": [0.0, 1.0, 0.0],
        "young": young,
        "poisson": 0.49,
        "damping_stiffness": 0.005,
    }
    doc = {
        "scene": {"frames": 48, "fps": 24.0, "substeps": substeps},
        "ground": {} if offset is None else {"offset": offset},
        "object": [body],
    }
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
    return size, lowest, float(np.abs(points - previous).max())


def drop(device: str, young: float, substeps: int, offset: float | None) -> str:
    """One 2 s drop; its line of figures."""
    size, lowest, moved = stiff_drop(device, young, substeps, offset)
    rests = -0.001 * size < min(lowest) and max(lowest) < 0.001 * size and moved < 0.001 * size
    return (
        f"{young:.0e} Pa, {24 * substeps} steps/s: lowest {100 * min(lowest) / size:+.3f} .. "
        f"{100 * max(lowest) / size:+.3f} %, moved {100 * moved / size:.4f} % in the last frame, "
        f"{'at rest' if rests else 'NOT at rest within 0.1 %'}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--offset", type=float, default=None, help="the ground's offset (default: the scene's)")
    parser.add_argument("--young", type=float, action="append", help="Young's modulus (Pa; repeatable)")
    parser.add_argument("--substeps", type=int, action="append", help="steps per 1/24 s frame (repeatable)")
    parser.add_argument("--runs", type=int, default=1)
    args = parser.parse_args()
    for young in args.young or [1e9, 1e8]:
        for substeps in args.substeps or [1, 2]:
            for _ in range(args.runs):
                print(drop(args.device, young, substeps, args.offset), flush=True)


if __name__ == "__main__":
    main()

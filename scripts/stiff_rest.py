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
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def one_run(device: str, offset: float) -> str:
    """One 2 s drop; its line of figures."""
    from test_stability import stiff_drop

    size, lowest, moved, sim = stiff_drop(device, offset)
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

"""Time the dense penetration check per frame: scene A at frame 40, and 16 copies of its armadillo overlapping.

    .venv/bin/python scripts/check_timing.py [--device cpu] [--cache-dir .warpfem-cache]

Prints milliseconds per check (the first, which builds the meshes, and the best of five after it) and the result.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--cache-dir", default=".warpfem-cache")
    parser.add_argument("--assets", type=Path, default=Path("../shared/assets"))
    args = parser.parse_args(argv)
    sys.path.insert(0, str(Path(__file__).parent))
    import bench

    import warpfem
    from warpfem.io.penetration import PenetrationCheck

    scene = bench.load_with_assets(Path("scenes/paper_a_armadillo_stack.toml"), args.assets).with_frames(60)
    sim = warpfem.Simulation(scene, device="cpu", cache_dir=args.cache_dir)
    for _ in range(40):
        sim.step_frame()
    points, faces = sim.dense_points(), [b.dense_faces for b in sim.model.bodies]
    extent = np.ptp(points[0], axis=0)
    pile = [points[0] + [0.8 * extent[0] * (k % 4), 0.0, 0.8 * extent[2] * (k // 4)] for k in range(16)]
    cases = {
        "scene A": (points, faces, sim.body_names),
        "16 armadillos": (pile, [faces[0]] * 16, [f"a{k}" for k in range(16)]),
    }
    for name, (p, f, names) in cases.items():
        check = PenetrationCheck(f, names, args.device)
        times = []
        for _ in range(6):
            clock = time.perf_counter()
            result = check.measure(p)
            times.append(time.perf_counter() - clock)
        count = sum(len(x) for x in p)
        print(
            f"{name}: {len(p)} bodies, {count:,} vertices: first {1e3 * times[0]:.0f} ms, "
            f"then {1e3 * min(times[1:]):.1f} ms ({1e8 * min(times[1:]) / count:.1f} ms per 100k vertices); {result}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Regenerate the README stills: run each scene to a frame and render it with warpfem's own renderer.

    .venv/bin/python scripts/make_stills.py                       the default scene -> docs/stills/default.png
    .venv/bin/python scripts/make_stills.py scenes/*.toml --frame 45 --size 640x480 --device cpu

One PNG per scene, named after the scene file, in --out-dir (default docs/stills). The frame defaults to
a quarter of the scene's frames (the first impact of a drop). Preprocessing uses the usual cache.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def still(scene_path: Path | None, out_dir: Path, frame: int | None, size: tuple[int, int], device: str) -> Path:
    """Run one scene to ``frame`` and write ``<out_dir>/<scene stem>.png``; returns the PNG path."""
    from PIL import Image

    import warpfem
    from warpfem.io.render import Renderer, auto_camera, framing_box

    scene = warpfem.load_scene(scene_path or warpfem.default_scene_path())
    target = frame if frame is not None else max(1, scene.frames // 4)
    sim = warpfem.Simulation(scene, device=device)
    for _ in range(target):
        sim.step_frame()
    points = sim.dense_points()
    obstacles = sim.obstacles_at()
    shapes = [o.vertices @ o.matrix[:3, :3].T + o.matrix[:3, 3] for o in obstacles]
    ground = scene.ground.height if scene.ground.enabled else None
    faces = [b.dense_faces for b in sim.model.bodies] + [o.faces for o in obstacles]
    renderer = Renderer(faces, *size, device=device, up_axis=scene.up_axis, ground=ground)
    box = framing_box(points + shapes, scene.up_axis, ground, margin=0.1)  # the frame shown, down to the ground
    renderer.camera = auto_camera(*box, scene.up_axis, size[0] / size[1])
    path = out_dir / f"{Path(scene.path).stem}.png"
    Image.fromarray(renderer.render(points + shapes)).save(path, optimize=True)
    return path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenes", nargs="*", type=Path, help="scene files (default: the shipped default scene)")
    parser.add_argument("--out-dir", type=Path, default=ROOT / "docs" / "stills")
    parser.add_argument("--frame", type=int, help="frame to show (default: 1/4 of each scene's frames)")
    parser.add_argument("--size", default="640x480", help="WIDTHxHEIGHT (default 640x480)")
    parser.add_argument("--device", default=None, help="Warp device (default: cuda:0 if present, else cpu)")
    args = parser.parse_args()
    import warp as wp

    from warpfem.io.render import parse_size

    wp.config.log_level = wp.LOG_WARNING
    device = args.device or ("cuda:0" if wp.is_cuda_available() else "cpu")
    args.out_dir.mkdir(parents=True, exist_ok=True)
    for scene in args.scenes or [None]:
        clock = time.perf_counter()
        path = still(scene, args.out_dir, args.frame, parse_size(args.size), device)
        print(f"{path}  ({path.stat().st_size / 1024:.0f} KiB, {time.perf_counter() - clock:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

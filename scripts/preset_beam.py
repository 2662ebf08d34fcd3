"""Each quality preset through the whole pipeline on a dense cantilever: tets, faces, time per frame, sag error.

A dense triangulated 1 x 0.1 x 0.1 m beam (E 1e7 Pa, nu 0.3 unless --poisson, 1000 kg/m^3) is prepared with
``[solver] quality`` set and nothing else, held still at x <= 0, damped to rest under gravity, and its
dense tip sag compared with NGSolve's converged nonlinear answer (computed here unless --reference-sag).

    .venv/bin/python scripts/preset_beam.py [--presets preview default high] [--device cpu]
        [--elements linear quadratic] [--cache-dir DIR] [--reference-sag 0.1447865891312432] [--json OUT.json]

``--elements`` runs each preset with each of those elements instead of its own; ``--json`` writes the rows
with the device, driver, Warp version and commit.

With --assets MESH..., prints instead what each preset makes of those meshes (tets and faces, sized by
thickness and, as before, by the bounding box alone) without simulating.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
from pathlib import Path

from warpfem.study.presets import measure, write_beam
from warpfem.study.reference import Cantilever


def assets_table(meshes: list[Path], presets: list[str]) -> int:
    """Print tets and coarse faces of each mesh at each preset, sized by thickness and by the bounding box."""
    import time

    from warpfem.prep.pipeline import prepare
    from warpfem.scene import PRESETS

    print("| mesh | preset | tets (bbox) | tets (thickness) | faces | thickness / diagonal | budget bound | prep s |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for mesh in meshes:
        for preset in presets:
            p = PRESETS[preset]
            plain = prepare(mesh, faces=p["faces"], maxh=p["maxh"], cache_dir=None)
            start = time.perf_counter()
            sized = prepare(
                mesh, p["faces"], maxh=p["maxh"], cache_dir=None, across=p["tets_across"], max_tets=p["max_tets"]
            )
            s = sized.stats
            print(
                f"| {mesh.name} | {preset} | {plain.stats['tets']} | {s['tets']} | {s['coarse_faces']} |"
                f" {s.get('thickness_relative', float('nan')):.4f} | {s.get('sizing_capped', '')} |"
                f" {time.perf_counter() - start:.1f} |",
                flush=True,
            )
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=["preview", "default", "high"])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--poisson", type=float, default=0.3)
    parser.add_argument("--reference-sag", type=float, default=None, help="NGSolve's converged sag (m), if known")
    parser.add_argument("--elements", nargs="+", choices=("linear", "quadratic"), default=[None])
    parser.add_argument("--cache-dir", type=Path, default=None, help="preprocessing cache (default: a new one)")
    parser.add_argument("--json", type=Path, default=None, help="also write the rows here")
    parser.add_argument("--assets", nargs="+", type=Path, default=None, help="mesh files to prepare instead")
    args = parser.parse_args()
    if args.assets:
        return assets_table(args.assets, args.presets)
    beam = Cantilever(poisson=args.poisson)
    reference = args.reference_sag
    if reference is None:
        from warpfem.study.reference import converged_sag

        reference = converged_sag(beam, nonlinear=True, rtol=1e-3, orders=(2, 3, 4)).sag
    print(f"NGSolve converged nonlinear sag: {1e3 * reference:.2f} mm (nu {beam.poisson})")
    print("| preset | elements | tets | coarse faces | ms/frame | sag mm | sag error |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    rows = []
    with tempfile.TemporaryDirectory() as work:
        mesh = write_beam(Path(work) / "beam.obj", beam)
        cache = args.cache_dir or Path(work) / "cache"
        for preset in args.presets:
            for elements in args.elements:
                point = measure(preset, mesh, reference, cache, beam, args.device, elements)
                rows.append(dataclasses.asdict(point))
                print(
                    f"| {preset} | {point.elements} | {point.tets} | {point.coarse_faces} | {point.ms_per_frame:.1f} |"
                    f" {1e3 * point.sag:.2f} | {100 * point.sag_error:+.1f} % |",
                    flush=True,
                )
    if args.json:
        import warp as wp

        sys.path.insert(0, str(Path(__file__).parent))
        from bench import environment

        run = environment(wp.get_device(args.device))
        args.json.write_text(json.dumps({**run, "reference_sag": reference, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

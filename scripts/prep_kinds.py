"""Run `warpfem prepare` on meshes of the kinds real collections hold, made by tests/mesh_kinds.py.

A scan with non-manifold edges (the stanford bunny with two flaps welded on), the same scan with flipped
faces, a triangle-strip PLY (the bunny), a sharp CAD part (an angle bracket), a flat open sheet, models of
44 shells (overlapping, and apart), two tets sharing an edge. Each run is a separate
`python -m warpfem prepare MESH --faces N --no-cache --json` process (scripts/sweep_assets.py's run_one), timed
whole, Python start-up included.

    .venv/bin/python scripts/prep_kinds.py [--faces 400 1000 2500] [--limit 300]

Writes scripts/results/prep-kinds-<date>.json and prints the Markdown table of docs/preprocessing.md.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import tempfile
from pathlib import Path

import numpy as np
import trimesh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "scripts"))

import mesh_kinds as kinds  # noqa: E402
from sweep_assets import ASSETS, run_one  # noqa: E402


def make_meshes(folder: Path) -> dict[str, Path]:
    """Write every kind into ``folder``; return {label: path}."""
    bunny = trimesh.load(ASSETS / "stanford-bunny.obj", process=False, force="mesh")
    rng = np.random.default_rng(1)
    apart = []
    for k in range(44):
        radius = rng.uniform(0.2, 0.4)
        part = trimesh.creation.icosphere(3, radius=radius) if k % 2 else trimesh.creation.box(extents=[0.5] * 3)
        apart.append(part.apply_translation(np.array([k % 11, (k // 11) % 2, k // 22], dtype=float)))
    merged = trimesh.util.concatenate(apart)
    return {
        "scan, 2 non-manifold edges (bunny + flaps)": kinds.write_obj(
            folder / "bunny_flaps.obj", *kinds.with_flaps(bunny.vertices, bunny.faces, 2)
        ),
        "scan, 5 flipped faces (bunny)": kinds.write_obj(
            folder / "bunny_flipped.obj", *kinds.with_flipped_faces(bunny.vertices, bunny.faces, 5)
        ),
        "triangle-strip binary PLY (bunny)": kinds.write_strip_ply(
            folder / "bunny_strips.ply", bunny.vertices, bunny.faces
        ),
        "sharp CAD part (angle bracket, STL)": _stl(folder / "bracket.stl", *kinds.cad_bracket()),
        "flat open sheet": kinds.write_obj(folder / "sheet.obj", *kinds.flat_sheet()),
        "44 shells, overlapping": kinds.write_obj(folder / "shells44.obj", *kinds.many_shells()),
        "44 shells, apart": kinds.write_obj(folder / "shells44_apart.obj", merged.vertices, merged.faces),
        "two tets sharing an edge": kinds.write_obj(folder / "bowtie.obj", *kinds.bowtie()),
    }


def _stl(path: Path, vertices: np.ndarray, faces: np.ndarray) -> Path:
    trimesh.Trimesh(vertices, faces, process=False).export(path)
    return path


def table(rows: list[tuple[str, dict]]) -> str:
    lines = [
        "| mesh | faces | outcome | rung | coarse faces | tets | worst dihedral (deg) | Hausdorff / diag | total s |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for label, r in rows:
        s = r.get("stats", {})
        if r["outcome"] == "ok":
            lines.append(
                f"| {label} | {r['faces']} | ok | {s['rung'].split(' ')[0]} | {s['coarse_faces']} | {s['tets']} |"
                f" {float(s['tet_min_dihedral_deg']):.3g} | {float(s['hausdorff_relative']):.3g} | {r['wall_s']} |"
            )
        else:
            message = r.get("message", "").removeprefix("warpfem: error: ")
            lines.append(f"| {label} | {r['faces']} | {r['outcome']}: {message} | | | | | | {r['wall_s']} |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--faces", type=int, nargs="+", default=[400, 1000, 2500])
    parser.add_argument("--limit", type=float, default=300.0, help="seconds per run before it counts as a hang")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory(prefix="warpfem-kinds-") as tmp:
        for label, path in make_meshes(Path(tmp)).items():
            for faces in args.faces:
                record = run_one(path, faces, args.limit)
                record["kind"] = label
                rows.append((label, record))
                print(json.dumps(record)[:300], flush=True)
    out = args.out or ROOT / "scripts" / "results" / f"prep-kinds-{datetime.date.today().isoformat()}.json"
    meta = {"machine": platform.platform(), "cpus": os.cpu_count(), "python": sys.version.split()[0]}
    out.write_text(json.dumps({"meta": meta, "runs": [r for _, r in rows]}, indent=1) + "\n")
    print(table(rows))
    return 1 if any(r["outcome"] in ("crash", "hang") for _, r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())

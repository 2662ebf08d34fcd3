"""Run `warpfem prepare` on every shared asset at several face counts and record what came out.

Each run is a separate `python -m warpfem prepare MESH --faces N --no-cache --json` process, so the sweep checks
exactly what a user gets: exit code 0 with stats, or a non-zero exit with one line on stderr (never a
traceback, never a crash, never a hang: a run over --limit seconds counts as a hang).

    .venv/bin/python scripts/sweep_assets.py [--faces 300 500 1000 2000 3000] [--limit 900]

Writes scripts/results/preprocessing-<date>.json and prints a Markdown table per asset.
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ASSETS = ROOT.parent / "shared" / "assets"
MESHES = ("armadillo.off", "horse.ply", "stanford-bunny.obj", "spot.obj", "cow.obj", "homer.obj")


def number(value) -> str:
    """A statistic as the table shows it: floats to four significant digits."""
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def run_one(mesh: Path, faces: int, limit: float) -> dict:
    cmd = [sys.executable, "-m", "warpfem", "prepare", str(mesh), "--faces", str(faces), "--no-cache", "--json"]
    clock = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=limit, cwd=ROOT)
    except subprocess.TimeoutExpired:
        return {"mesh": mesh.name, "faces": faces, "rc": None, "outcome": "hang", "wall_s": limit}
    wall = time.perf_counter() - clock
    errors = [line for line in proc.stderr.splitlines() if line.startswith("warpfem:") or "Traceback" in line]
    record = {"mesh": mesh.name, "faces": faces, "rc": proc.returncode, "wall_s": round(wall, 2)}
    if proc.returncode == 0:
        record.update(outcome="ok", stats=json.loads(proc.stdout))
    else:
        clean = proc.returncode > 0 and "Traceback" not in proc.stderr and len(errors) == 1
        record.update(outcome="error" if clean else "crash", message=errors[-1] if errors else proc.stderr[-500:])
    return record


def table(records: list[dict]) -> str:
    rows = [
        "| asset | faces | outcome | rung | tets | min dihedral (deg) | volume ratio | Hausdorff / diag |"
        " simplify s | Netgen s | total s |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in records:
        s = r.get("stats", {})
        if r["outcome"] == "ok":
            rows.append(
                f"| {r['mesh']} | {r['faces']} | ok | {s['rung'].split(' ')[0]} | {s['tets']} |"
                f" {number(s['tet_min_dihedral_deg'])} | {number(s['volume_ratio'])} |"
                f" {number(s['hausdorff_relative'])} |"
                f" {float(s['seconds_simplify']) + float(s.get('seconds_outer', 0)):.3g} |"
                f" {number(s['seconds_tetrahedralize'])} | {r['wall_s']} |"
            )
        else:
            rows.append(f"| {r['mesh']} | {r['faces']} | {r['outcome']}: {r.get('message', '')} | | | | | | | | |")
    return "\n".join(rows)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--faces", type=int, nargs="+", default=[300, 500, 1000, 2000, 3000])
    parser.add_argument("--meshes", nargs="+", default=list(MESHES))
    parser.add_argument("--limit", type=float, default=900.0, help="seconds per run before it counts as a hang")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    records = []
    for name in args.meshes:
        for faces in args.faces:
            record = run_one(ASSETS / name, faces, args.limit)
            records.append(record)
            print(json.dumps(record)[:300], flush=True)
    out = args.out or ROOT / "scripts" / "results" / f"preprocessing-{datetime.date.today().isoformat()}.json"
    meta = {"machine": platform.platform(), "cpus": __import__("os").cpu_count(), "python": sys.version.split()[0]}
    out.write_text(json.dumps({"meta": meta, "runs": records}, indent=1) + "\n")
    print(table(records))
    bad = [r for r in records if r["outcome"] in ("crash", "hang")]
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())

"""The Newton peer benchmark harness, in its quick CPU mode (skipped where newton is not installed)."""

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("newton")

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_quick_newton_benchmark_writes_a_complete_json(tmp_path):
    cache = tmp_path / "cache"
    cmd = [sys.executable, str(ROOT / "scripts" / "bench_newton.py"), "--quick", "--out", str(tmp_path)]
    done = subprocess.run(cmd + ["--cache-dir", str(cache)], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    (path,) = tmp_path.glob("bench-newton-cpu-*.json")
    result = json.loads(path.read_text())
    env = result["environment"]
    assert env["warp"] and env["commit"] and env["device_alias"] == "cpu" and env["newton"]
    assert result["mode"] == "quick"
    settings = result["settings"]
    assert settings["solver"] == "SolverVBD" and settings["self_contact"]
    assert (settings["substeps"], settings["iterations"]) == (10, 10)
    (run,) = result["runs"]
    assert run["n"] == 1 and run["bodies"] == 1 and run["frames_timed"] == 3

    # the same tet mesh as warpfem's own pile: every tet and vertex kept
    from warpfem.prep.pipeline import prepare

    body = prepare("builtin:bunny", faces=300, cache_dir=cache)
    assert run["tets"] == len(body.tets) and run["particles"] == len(body.tet_vertices)

    assert run["ms_per_frame"] > 0 and not run["nan"]
    # 5 frames after the drop from 0.7 m: still falling, above the ground
    assert math.isfinite(run["lowest_point_m"]) and 0.0 < run["lowest_point_m"] < 1.0
    # its dense mesh carried by Newton's tets, checked on every frame of the run: still in the air
    check = run["dense_check"]
    assert check["frames"] == [1, 2, 3, 4, 5] and check["end"]["below_relative"] == 0.0
    assert check["worst"]["relative"] == 0.0 and check["by_frame"]["below"] == [0.0] * 5

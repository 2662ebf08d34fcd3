"""The tradeoff sweep: Pareto front, scoring against references, CSV and plot, the command."""

import csv
from pathlib import Path

import numpy as np
import pytest

from warpfem.cli import main
from warpfem.errors import InputError
from warpfem.scene import PRESETS
from warpfem.study.reference import Cantilever
from warpfem.study.tradeoff import BeamScene, Setting, pareto_front, plot, run_setting, score, write_csv


def test_pareto_front_against_brute_force():
    rng = np.random.default_rng(3)
    cost, err = rng.random(40), rng.random(40)
    cost[5], err[5] = cost[6], err[6]  # a tie: neither dominates the other
    front = pareto_front(cost, err)
    for i in range(40):
        beaten = any(
            cost[j] <= cost[i] and err[j] <= err[i] and (cost[j] < cost[i] or err[j] < err[i]) for j in range(40)
        )
        assert front[i] == (not beaten)


def test_bad_setting_is_input_error():
    with pytest.raises(InputError, match="cg_mode"):
        Setting(cg_mode="adaptive")
    with pytest.raises(InputError, match="cells"):
        Setting(cells=0)
    with pytest.raises(InputError, match="rotation_updates"):
        Setting(rotation_updates=-1)
    with pytest.raises(InputError, match="elements"):
        Setting(elements="cubic")


SCENE = BeamScene(beam=Cantilever(young=1e7), seconds=0.25, dense_cells=2)


def test_sweep_rows_are_consistent(device, tmp_path):
    fine = run_setting(SCENE, Setting("reference", cells=2, substeps=4, cg_tolerance=1e-6, cg_iterations=2000), device)
    runs = [
        run_setting(SCENE, Setting("a", cells=1, substeps=1, cg_mode="fixed", cg_iterations=5), device),
        run_setting(SCENE, Setting("b", cells=2, substeps=4, cg_tolerance=1e-6, cg_iterations=2000), device),
        run_setting(SCENE, Setting("c", cells=1, substeps=1, cg_tolerance=1e-6, rotation_updates=0), device),
        run_setting(SCENE, Setting("d", cells=1, substeps=4, cg_tolerance=1e-6, elements="quadratic"), device),
    ]
    assert runs[0].tets == 60 and runs[1].tets == 480
    assert runs[0].cg_iterations_per_step == 5
    rows = score(SCENE, runs, fine, reference_sag=0.1)
    assert rows[1].trajectory_error < 1e-6  # the same setting as the reference: the same trajectory
    assert rows[0].trajectory_error > 1e-3
    # the beam falls: 0.25 s of free fall would be g t^2 / 2 = 0.31 m; clamped, it sags far less but > 0
    assert 0.0 < rows[1].sag < 0.3
    write_csv(tmp_path / "t.csv", rows)
    with open(tmp_path / "t.csv") as f:
        table = list(csv.DictReader(f))
    assert [r["knob"] for r in table] == ["a", "b", "c", "d"]
    assert [r["rotation_updates"] for r in table] == ["default", "default", "0", "default"]
    assert [r["elements"] for r in table] == ["linear", "linear", "linear", "quadratic"]
    assert runs[3].tets == 60 and runs[3].setting.label.endswith(", quadratic")
    assert runs[2].setting.label == "cells 1, 1 substeps, CG tol 1e-06, 0 rotation updates"
    assert float(table[1]["trajectory_error_m"]) == pytest.approx(rows[1].trajectory_error, rel=1e-3, abs=1e-9)
    plot(tmp_path / "t.png", rows, "test")
    assert (tmp_path / "t.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_presets_use_scene_keys():
    keys = {"substeps", "cg_mode", "cg_iterations", "cg_tolerance", "elements", "faces", "maxh", "tets_across"}
    for preset in PRESETS.values():
        assert set(preset) == keys | {"max_tets"}
        assert preset["cg_mode"] in ("fixed", "tolerance")
        assert preset["elements"] in ("linear", "quadratic")


def test_command_rejects_a_file_as_out(tmp_path, capsys):
    (tmp_path / "f").write_text("")
    assert main(["tradeoff", "--quick", "--out", str(tmp_path / "f")]) == 2
    assert "not a folder" in capsys.readouterr().err


def test_plot_from_an_existing_csv(tmp_path):
    from PIL import Image

    from warpfem.cli import main

    csv_path = Path(__file__).resolve().parents[1] / "scripts" / "results" / "tradeoff-quick-cpu" / "tradeoff.csv"
    assert main(["tradeoff", "--plot-from", str(csv_path), "--out", str(tmp_path)]) == 0
    with Image.open(tmp_path / "tradeoff.png") as image:
        assert image.size[0] > 500 and image.size[1] > 300
    assert main(["tradeoff", "--plot-from", str(tmp_path / "missing.csv"), "--out", str(tmp_path)]) == 2


def test_contact_sweep_covers_every_penalty(device):
    from warpfem.study.tradeoff import PENALTIES, contact_sweep

    rows = contact_sweep(device, frames=60, cells=2)
    assert [r.stiffness for r in rows] == list(PENALTIES)
    for r in rows:
        assert r.ms_per_frame > 0 and np.isfinite(r.impact_depth) and r.cg_iterations_per_step > 0
        assert 0.0 < r.impact_depth < 0.5 * 0.15  # the cubes met and none passed through
    soft, firm = rows[0], rows[2]
    assert firm.resting_depth < soft.resting_depth  # a softer penalty lets the cube sink further
    for r in rows:  # flagged on the front exactly when no other penalty is as fast and as shallow, and better
        beaten = any(
            o.ms_per_frame <= r.ms_per_frame
            and o.impact_depth <= r.impact_depth
            and (o.ms_per_frame < r.ms_per_frame or o.impact_depth < r.impact_depth)
            for o in rows
        )
        assert r.pareto == (not beaten)


def test_bad_reference_sag_is_one_line_exit_2(tmp_path, capsys):
    from warpfem.cli import main

    assert main(["tradeoff", "--quick", "--out", str(tmp_path / "t"), "--reference-sag", "-1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--reference-sag" in err[0]
    assert not (tmp_path / "t").exists()

"""`warpfem run` reproduces a reference run: two balls landing on the ground and on each other (CPU).

The reference (tests/data/golden/two_balls_frames.npz) is a run of the current physics: a change that alters
the physics on purpose regenerates it and says so in its commit; any other change must leave it as it is.
"""

from pathlib import Path

import numpy as np
from pxr import Usd, UsdGeom

from warpfem.cli import main

GOLDEN = Path(__file__).resolve().parent / "data" / "golden"


def test_run_output_matches_the_reference_run(tmp_path):
    out = tmp_path / "two_balls.usdc"
    args = ["run", str(GOLDEN / "two_balls.toml"), "--out", str(out), "--device", "cpu", "--no-cache", "--quiet"]
    assert main(args) == 0
    stage = Usd.Stage.Open(str(out))
    reference = np.load(GOLDEN / "two_balls_frames.npz")
    for key in reference.files:
        name, frame = key.rsplit("_", 1)
        points = np.array(UsdGeom.Mesh(stage.GetPrimAtPath(f"/World/{name}")).GetPointsAttr().Get(int(frame)))
        np.testing.assert_allclose(points, reference[key], rtol=0, atol=1e-6, err_msg=key)
    # the reference itself is a real landing: the lower ball rests on the ground, the upper one on it
    assert reference["ball_20"][:, 1].min() > -0.01 and reference["top_20"][:, 1].min() < 0.3


def test_every_nth_frame_writes_those_frames_of_the_same_run(tmp_path):
    """--every 3: samples at 0, 3, ..., 18 and the last frame, 20, equal to the reference run's."""
    out = tmp_path / "sparse.usdc"
    args = ["run", str(GOLDEN / "two_balls.toml"), "--out", str(out), "--device", "cpu", "--no-cache", "--quiet"]
    assert main([*args, "--every", "3"]) == 0
    stage = Usd.Stage.Open(str(out))
    attr = UsdGeom.Mesh(stage.GetPrimAtPath("/World/top")).GetPointsAttr()
    assert attr.GetTimeSamples() == [0.0, 3.0, 6.0, 9.0, 12.0, 15.0, 18.0, 20.0]
    reference = np.load(GOLDEN / "two_balls_frames.npz")
    np.testing.assert_allclose(np.array(attr.Get(20)), reference["top_20"], rtol=0, atol=1e-6)


def test_every_below_one_is_a_one_line_error_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "none.usdc"
    args = ["run", str(GOLDEN / "two_balls.toml"), "--out", str(out), "--device", "cpu", "--no-cache", "--every", "0"]
    assert main(args) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("warpfem:")]
    assert len(err) == 1 and "--every must be >= 1" in err[0]
    assert list(tmp_path.iterdir()) == []

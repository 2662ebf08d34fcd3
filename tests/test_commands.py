"""The CLI's preview, render, info, --json and --help, end to end on a tiny scene on the CPU."""

import contextlib
import io
import json

import numpy as np
import pytest
import trimesh
from PIL import Image
from pxr import Usd, UsdGeom
from test_render import object_mask, project

from warpfem.cli import main
from warpfem.io.render import auto_camera, framing_box

SCENE = """
[scene]
frames = 12
substeps = 2
[[object]]
name = "ball"
mesh = "ball.obj"
faces = 120
scale = 0.4
translate = [0.0, 0.6, 0.0]
young = 1e5
"""
W, H = 96, 72


def _run(*args):
    return main([str(a) for a in args])


def _one_line_error(capsys, *needles):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("warpfem: error: "), err
    for needle in needles:
        assert needle in err[0], err[0]


def _usd_frames(path):
    stage = Usd.Stage.Open(str(path))
    attr = UsdGeom.Mesh(stage.GetPrimAtPath("/World/ball")).GetPointsAttr()
    return [np.array(attr.Get(t), dtype=np.float64) for t in attr.GetTimeSamples()]


def _gif_frames(path):
    with Image.open(path) as gif:
        frames = []
        for k in range(gif.n_frames):
            gif.seek(k)
            frames.append(np.asarray(gif.convert("RGB")))
    return frames


def _centroid(image):
    rows, cols = np.nonzero(object_mask(image))
    return np.array([cols.mean() + 0.5, rows.mean() + 0.5])


@pytest.fixture(scope="module")
def ran(tmp_path_factory):
    """One run of the ball scene with a GIF preview and a JSON summary."""
    folder = tmp_path_factory.mktemp("ran")
    trimesh.creation.icosphere(subdivisions=3).export(folder / "ball.obj")
    (folder / "scene.toml").write_text(SCENE)
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        code = _run(
            *("run", folder / "scene.toml", "--out", folder / "anim.usdc", "--device", "cpu", "--no-cache"),
            *("--json", "--preview", folder / "anim.gif", "--size", f"{W}x{H}"),
        )
    return folder, code, json.loads(stdout.getvalue())


def test_run_preview_shows_the_ball_where_the_simulation_put_it(ran):
    folder, code, summary = ran
    assert code == 0
    assert summary["frames"] == 12 and summary["preview"].endswith("anim.gif") and summary["preview_size"] == [W, H]
    assert summary["seconds"]["render"] > 0 and summary["dense_triangles"] == 1280
    images = _gif_frames(folder / "anim.gif")
    points = _usd_frames(folder / "anim.usdc")
    assert len(images) == len(points) == 13 and images[0].shape == (H, W, 3)
    # the automatic camera frames frame 0 down to the ground; project each frame's ball centre with NumPy
    camera = auto_camera(*framing_box([points[0]], "Y", 0.0, margin=0.2), "Y", W / H)
    rows = []
    for image, p in zip(images, points, strict=True):
        centre = 0.5 * (p.min(axis=0) + p.max(axis=0))
        np.testing.assert_allclose(_centroid(image), project(camera, centre, W, H)[0], atol=1.5)
        rows.append(_centroid(image)[1])
    assert rows[-1] > rows[0] + 2  # it fell: its pixels moved down


def test_render_command_writes_mp4_and_png_frames(ran, capsys):
    import imageio_ffmpeg

    folder = ran[0]
    capsys.readouterr()
    assert _run("render", folder / "anim.usdc", "--out", folder / "anim.mp4", "--size", f"{W}x{H}", "--quiet") == 0
    assert "render per frame" in capsys.readouterr().out
    reader = imageio_ffmpeg.read_frames(str(folder / "anim.mp4"))
    meta = next(reader)
    assert tuple(meta["size"]) == (W, H) and meta["fps"] == 60.0
    decoded = [np.frombuffer(b, dtype=np.uint8).reshape(H, W, 3) for b in reader]
    assert len(decoded) == 13
    assert _run("render", folder / "anim.usdc", "--out", folder / "png", "--size", f"{W}x{H}", "--json") == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames"] == 13 and summary["format"] == "png" and summary["meshes"] == ["/World/ball"]
    pngs = sorted((folder / "png").iterdir())
    assert len(pngs) == 13
    first, last = (np.asarray(Image.open(p).convert("RGB")) for p in (pngs[0], pngs[-1]))
    assert _centroid(last)[1] > _centroid(first)[1] + 2
    # H.264 is lossy; the decoded video still matches the lossless PNG frames closely
    assert np.abs(decoded[6].astype(int) - np.asarray(Image.open(pngs[6]).convert("RGB")).astype(int)).mean() < 6


@pytest.mark.parametrize(
    "args, needles",
    [
        (["render", "{f}/missing.usdc", "--out", "{f}/x.mp4"], ("missing.usdc", "no such file")),
        (["render", "{f}/scene.toml", "--out", "{f}/x.mp4"], ("scene.toml", "not a USD file")),
        (["render", "{f}/anim.usdc", "--out", "{f}/x.avi"], ("x.avi", ".mp4")),
        (["render", "{f}/anim.usdc", "--out", "{f}/x.mp4", "--size", "99x70"], ("--size",)),
        (["render", "{f}/anim.usdc", "--out", "{f}/x.mp4", "--camera", "1,2"], ("--camera",)),
        (["render", "{f}/anim.usdc", "--out", "{f}/x.mp4", "--fov", "190"], ("--fov",)),
        (["run", "{f}/scene.toml", "--out", "{f}/y.usdc", "--preview", "{f}/y.png"], ("y.png", "folder")),
        (["run", "{f}/scene.toml", "--out", "{f}/y.usdc", "--preview", "{f}/no/y.gif"], ("does not exist",)),
        (["run", "{f}/nothere.toml", "--out", "{f}/y.usdc", "--preview", "{f}/y.gif"], ("nothere.toml",)),
        (["prepare", "{f}/ball.obj", "--budget", "0", "--cache-dir", "{f}/c"], ("--budget", "> 0")),
        (["prepare", "{f}/ball.obj", "--budget", "nan", "--cache-dir", "{f}/c"], ("--budget", "nan")),
        (["prepare", "{f}/ball.obj", "--timeout", "inf", "--cache-dir", "{f}/c"], ("--timeout", "inf")),
        (["prepare", "{f}/ball.obj", "--quality", "best"], ("--quality", "invalid choice", "warpfem prepare --help")),
        (["run", "{f}/scene.toml", "--frames", "ten"], ("--frames", "invalid int value", "warpfem run --help")),
        (["run", "{f}/scene.toml", "--fast"], ("unrecognized arguments: --fast",)),
        (["simulate", "{f}/scene.toml"], ("invalid choice: 'simulate'",)),
    ],
)
def test_bad_input_is_one_line_exit_2_and_no_output(ran, capsys, args, needles):
    folder = ran[0]
    before = sorted(p.name for p in folder.iterdir())
    capsys.readouterr()
    assert _run(*[a.format(f=folder) for a in args]) == 2
    _one_line_error(capsys, *needles)
    assert sorted(p.name for p in folder.iterdir()) == before


def test_bad_mesh_with_preview_leaves_nothing(tmp_path, capsys):
    (tmp_path / "ball.obj").write_text("v 0 0 0\n")
    (tmp_path / "scene.toml").write_text(SCENE)
    args = ["run", tmp_path / "scene.toml", "--out", tmp_path / "a.usdc", "--preview", tmp_path / "a.mp4"]
    assert _run(*args, "--device", "cpu", "--no-cache") == 2
    _one_line_error(capsys, "ball.obj")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ball.obj", "scene.toml"]


def test_interrupted_run_keeps_preview_frames(tmp_path, capsys, monkeypatch):
    import warpfem.simulation as simulate

    trimesh.creation.icosphere(subdivisions=2).export(tmp_path / "ball.obj")
    (tmp_path / "scene.toml").write_text(SCENE)
    calls = {"n": 0}
    original = simulate.Simulation.advance

    def advance(self, timer=None):
        calls["n"] += 1
        if calls["n"] == 4:
            raise KeyboardInterrupt
        original(self, timer)

    monkeypatch.setattr(simulate.Simulation, "advance", advance)
    args = ["run", tmp_path / "scene.toml", "--out", tmp_path / "a.usdc", "--preview", tmp_path / "a.gif"]
    assert _run(*args, "--size", "32x24", "--device", "cpu", "--no-cache", "--quiet") == 130
    assert "a.gif" in capsys.readouterr().err
    assert len(_gif_frames(tmp_path / "a.gif")) == len(_usd_frames(tmp_path / "a.usdc")) == 4
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.gif", "a.usdc", "ball.obj", "scene.toml"]


def test_info_reports_versions_and_devices(capsys):
    import warp as wp

    assert _run("info", "--json") == 0
    info = json.loads(capsys.readouterr().out)
    assert info["versions"]["warp-lang"] == wp.__version__
    assert info["gpu_found"] == bool(wp.get_cuda_devices())
    assert "cpu" in [d["alias"] for d in info["devices"]]
    assert info["ffmpeg"] and not info["ffmpeg"].startswith("unavailable")
    assert _run("info") == 0
    table = capsys.readouterr().out
    assert "GPU found" in table and "pillow" in table


@pytest.mark.parametrize("command", ["run", "render", "prepare", "info"])
def test_help_has_examples_and_exit_codes(command, capsys):
    with pytest.raises(SystemExit) as done:
        main([command, "--help"])
    assert done.value.code == 0
    text = capsys.readouterr().out
    assert "examples:" in text and "exit codes" in text and f"warpfem {command}" in text

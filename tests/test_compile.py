"""Kernel compilation: once per machine, never per scene; `warpfem warmup`; the first run says it compiles.

The subprocess tests give each run a fresh Warp kernel cache (``WARP_CACHE_PATH``) and count the compiled
binaries Warp leaves in it: Warp's own record of what was compiled, not warpfem's.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import trimesh
import warp as wp

import warpfem
from warpfem.sim.modules import STEP_MODULES, variants

BINARIES = (".o", ".cubin", ".ptx")

ONE_BALL = """
[scene]
frames = 1
substeps = 2
[[object]]
name = "ball"
mesh = "ball.obj"
faces = 120
scale = 0.2
translate = [0.0, 0.3, 0.0]
"""

THREE_BALLS = """
[scene]
frames = 1
substeps = 3
[[obstacle]]
kind = "sphere"
center = [0.6, 0.0, 0.0]
radius = 0.2
keys = [[0, 0, 0, 0, 0, 0, 0], [1, 0, 0.05, 0, 0, 0, 0]]
[[obstacle]]
kind = "mesh"
mesh = "ball.obj"
scale = 0.15
translate = [-0.6, 0.15, 0.0]
[[handle]]
object = "b"
min = [-0.5, 1.15, -0.5]
max = [0.7, 1.5, 0.5]
keys = [[0, 0, 0, 0, 0, 0, 0], [1, 0.1, 0, 0, 0, 0, 0]]
[[object]]
name = "a"
mesh = "ball.obj"
faces = 300
scale = 0.3
translate = [0.0, 0.35, 0.0]
self_collision = true
[[object]]
name = "b"
mesh = "ball.obj"
faces = 300
scale = 0.3
translate = [0.1, 1.0, 0.0]
[[object]]
name = "c"
mesh = "ball.obj"
faces = 120
scale = 0.2
translate = [0.6, 0.5, 0.0]
"""


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """The two scenes' folder, with a preprocessing cache shared by this module's tests."""
    folder = tmp_path_factory.mktemp("scenes")
    trimesh.creation.icosphere(subdivisions=3).export(folder / "ball.obj")
    (folder / "one.toml").write_text(ONE_BALL)
    (folder / "three.toml").write_text(THREE_BALLS)
    return folder


def _binaries(cache: Path) -> list[str]:
    return sorted(str(p.relative_to(cache)) for p in cache.rglob("*") if p.suffix in BINARIES)


def _warpfem(cache: Path, scenes: Path, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "WARP_CACHE_PATH": str(cache), "WARPFEM_CACHE": str(scenes / "prep")}
    done = subprocess.run(
        [sys.executable, "-m", "warpfem", *args], capture_output=True, text=True, env=env, timeout=600
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return done


def _run(cache: Path, scenes: Path, scene: str, device: str) -> tuple[dict, str]:
    """``warpfem run`` of one scene: its JSON summary and its stderr."""
    out = scenes / f"{scene}-{device.replace(':', '')}.usdc"
    done = _warpfem(
        cache, scenes, "run", str(scenes / scene), "--device", device, "--out", str(out), "--overwrite", "--json"
    )
    return json.loads(done.stdout), done.stderr


@pytest.mark.slow
def test_kernels_compile_once_per_machine_never_per_scene(scenes, tmp_path, device):
    """On a fresh kernel cache the first run compiles, says so and times it apart from the frames; a scene of
    other sizes and body count (tets, collision points, moving and mesh obstacles, a handle, self-collision)
    then compiles nothing;
    `warpfem warmup` compiles every variant it lists, after which a run compiles nothing either."""
    cache = tmp_path / "kernels"
    first, said = _run(cache, scenes, "one.toml", device)
    assert "compiling kernels (first run only)" in said
    assert first["seconds"]["compile"] > 0.5  # its own phase ...
    assert first["seconds"]["simulate"] < first["seconds"]["compile"]  # ... and not inside the frame
    compiled = _binaries(cache)
    assert compiled
    second, said = _run(cache, scenes, "three.toml", device)
    assert (second["bodies"], first["bodies"]) == (3, 1) and second["tets"] > 2 * first["tets"]
    assert "compiling kernels" not in said
    assert _binaries(cache) == compiled

    report = json.loads(_warpfem(cache, scenes, "warmup", "--device", device, "--json").stdout)
    before, compiled = compiled, _binaries(cache)
    assert report["compiled"] > 0  # the renderer's and preprocessing's modules, at least
    assert len(compiled) - len(before) == report["compiled"]  # one new binary per variant it says it compiled
    summary, said = _run(cache, scenes, "one.toml", device)
    assert "compiling kernels" not in said and summary["seconds"]["compile"] < first["seconds"]["compile"]
    assert _binaries(cache) == compiled
    assert json.loads(_warpfem(cache, scenes, "warmup", "--device", device, "--json").stdout)["compiled"] == 0


def test_every_launch_of_a_step_is_a_loaded_variant(scenes, device, monkeypatch):
    """Each kernel a simulation launches (bodies colliding, obstacles, a handle, ground, late contacts, the dense map)
    belongs to a module of STEP_MODULES, in a block size listed there: what Simulation loads up front and
    warmup compiles is what the step uses."""
    cpu = wp.get_device(device).is_cpu
    launched = set()
    for name in ("launch", "launch_tiled"):
        original = getattr(wp, name)

        def spy(kernel, *args, original=original, **kwargs):
            launched.add((kernel.module.name, 1 if cpu else int(kwargs.get("block_dim") or 256)))
            return original(kernel, *args, **kwargs)

        monkeypatch.setattr(wp, name, spy)
    sim = warpfem.Simulation(warpfem.load_scene(scenes / "three.toml"), device=device, cache_dir=scenes / "prep")
    for _ in range(3):
        sim.step_frame()
    sim.dense_points()
    modules = {name for name, _ in launched}
    assert {
        "warpfem.kernels.fem",
        "warpfem.kernels.collision",
        "warpfem.kernels.cg",
        "warpfem.kernels.drive",
    } <= modules
    assert launched <= set(variants(STEP_MODULES, sim.device))


def test_warmup_refuses_an_unknown_device_in_one_line(capsys):
    from warpfem.cli import main

    assert main(["warmup", "--device", "cuda:77"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [err[0]] and err[0].startswith("warpfem: error: --device cuda:77: no such device")


def test_no_kernel_module_compiles_backward_code():
    """Nothing in warpfem is differentiated: every module of ``warpfem.kernels`` that defines a kernel turns Warp's
    backward code off, which would otherwise be most of a first run's compile time (and ask ``cg_solve_shared`` for
    twice its shared memory)."""
    import importlib

    kernels = Path(warpfem.__file__).resolve().parents[1] / "kernels"
    with_kernels = []
    for path in sorted(kernels.glob("*.py")):
        module = importlib.import_module(f"warpfem.kernels.{path.stem}")
        if any(isinstance(value, wp.Kernel) for value in vars(module).values()):
            with_kernels.append(path.stem)
            assert wp.get_module(module.__name__).options["enable_backward"] is False, path.stem
    assert {"cg", "collision", "fem", "integrate"} <= set(with_kernels)

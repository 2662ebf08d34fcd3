"""warpfem: dense surface meshes animated through simplified tetrahedral meshes, in NVIDIA Warp.

The public API (docs/api.md)::

    import warpfem

    scene = warpfem.load_scene("scenes/default.toml")
    sim = warpfem.Simulation(scene, device="cpu")
    for _ in range(30):
        sim.step_frame()
    points = sim.dense_points("bunny")
    summary = warpfem.run(scene, out="bunny.usdc", frames=30)

Names are imported on first use, so ``import warpfem`` (and the CLI's ``--help``) stays light.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

_EXPORTS = {
    "Scene": "warpfem.scene",
    "load_scene": "warpfem.scene",
    "default_scene_path": "warpfem.scene",
    "InputError": "warpfem.errors",
    "SimulationError": "warpfem.errors",
    "Simulation": "warpfem.simulation",
    "FrameStats": "warpfem.simulation",
    "RunTotals": "warpfem.simulation",
    "run": "warpfem.runner",
    "RunSummary": "warpfem.runner",
    "Penetration": "warpfem.io.penetration",
    "frame_penetration": "warpfem.io.penetration",
    "add_body": "warpfem.build",
    "Model": "warpfem.sim.model",
    "ModelBuilder": "warpfem.sim.model",
    "State": "warpfem.sim.model",
    "Solver": "warpfem.sim.solver",
    "prepare": "warpfem.prep.pipeline",
    "PreparedBody": "warpfem.prep.pipeline",
    "warmup": "warpfem.compilation",
}

__all__ = [
    "__version__",
    "Scene",
    "load_scene",
    "default_scene_path",
    "InputError",
    "SimulationError",
    "Simulation",
    "FrameStats",
    "RunTotals",
    "run",
    "RunSummary",
    "Penetration",
    "frame_penetration",
    "add_body",
    "Model",
    "ModelBuilder",
    "State",
    "Solver",
    "prepare",
    "PreparedBody",
    "warmup",
]

if TYPE_CHECKING:
    from warpfem.build import add_body
    from warpfem.compilation import warmup
    from warpfem.errors import InputError, SimulationError
    from warpfem.io.penetration import Penetration, frame_penetration
    from warpfem.prep.pipeline import PreparedBody, prepare
    from warpfem.runner import RunSummary, run
    from warpfem.scene import Scene, default_scene_path, load_scene
    from warpfem.sim.model import Model, ModelBuilder, State
    from warpfem.sim.solver import Solver
    from warpfem.simulation import FrameStats, RunTotals, Simulation


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'warpfem' has no attribute '{name}'")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)

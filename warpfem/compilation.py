"""Compiling warpfem's Warp kernels ahead of any run: :func:`warmup` (``warpfem warmup``).

Warp compiles each module the first time it is used and keeps the binary in its kernel cache, per device
and block size. A run compiles what it is missing itself (:class:`~warpfem.Simulation` says so); warming up
once on a fresh machine, or in an image build, compiles every module a run, preprocessing or a preview can
load, so no later command of any scene compiles anything.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import warp as wp

from warpfem.sim.launch import WIDE_BLOCK
from warpfem.sim.modules import STEP_MODULES, ModuleLoad, load_modules

OUTPUT_MODULES = {"warpfem.kernels.penetration": (WIDE_BLOCK,), "warpfem.kernels.render": (WIDE_BLOCK,)}
"""The run's penetration check and the preview renderer, on the simulation's device."""

HOST_MODULES = {"warpfem.kernels.penetration": (WIDE_BLOCK,)}
"""What a run on a GPU also loads on the CPU: the penetration check's mesh obstacles, on the check's thread."""

PREP_MODULES = {
    "warpfem.kernels.distance": (WIDE_BLOCK,),
    "warpfem.kernels.embedding": (WIDE_BLOCK,),
    "warpfem.kernels.intersect": (WIDE_BLOCK,),
}
"""Preprocessing's modules; preprocessing runs on the CPU only."""


def warmup(devices: Sequence[str] | None = None, notify: Callable[[str], None] | None = None) -> list[ModuleLoad]:
    """Compile (or load, where Warp's kernel cache has them) every Warp module of warpfem on ``devices``.

    Each device gets every block-size variant of the simulation's modules, the penetration check's and the
    renderer's; the CPU also gets preprocessing's, and where only GPUs are named, the CPU still gets the
    penetration check's (a run checks its mesh obstacles there).

    Args:
        devices: Warp device names; None: every device here (the CPU and each GPU).
        notify: As for :func:`~warpfem.sim.modules.load_modules` (before and after a compile).

    Returns:
        One entry per module variant and device: whether it was compiled, and its load time.

    Raises:
        InputError: A device that is not here.
    """
    from warpfem.simulation import check_device

    for name in devices or ():
        check_device(name)
    wp.init()
    chosen = [wp.get_device(name) for name in devices] if devices else wp.get_devices()
    plan = [(d, STEP_MODULES | OUTPUT_MODULES | (PREP_MODULES if d.is_cpu else {})) for d in chosen]
    if not any(d.is_cpu for d in chosen):
        plan.append((wp.get_device("cpu"), HOST_MODULES))
    return load_modules(plan, notify)

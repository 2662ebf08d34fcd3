"""The Warp modules the simulation launches, in every block size it launches them with, loaded up front.

Warp compiles a module the first time one of its kernels is launched (seconds per module on a CPU, more
with CUDA) and keeps the binary in its kernel cache (``wp.config.kernel_cache_dir``), once per block size.
Loading every module a step can use before the model is built keeps compilation out of the step and its
timing, lets a first run say that it is compiling, and, with block sizes from a fixed set
(:mod:`warpfem.sim.launch`), means a scene never compiles what another scene did not.
"""

from __future__ import annotations

import importlib
import os
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import warp as wp

from warpfem.kernels.cg import HELD_WIDE_BLOCK
from warpfem.sim.launch import SPREAD_BLOCKS, WIDE_BLOCK

STEP_MODULES: dict[str, tuple[int, ...]] = {
    "warpfem.kernels.approach": (WIDE_BLOCK,),
    "warpfem.kernels.cg": (WIDE_BLOCK, HELD_WIDE_BLOCK),
    "warpfem.kernels.collision": SPREAD_BLOCKS,
    "warpfem.kernels.contacts": (WIDE_BLOCK,),
    "warpfem.kernels.deflation": (WIDE_BLOCK,),
    "warpfem.kernels.drive": (WIDE_BLOCK,),
    "warpfem.kernels.embedding": (WIDE_BLOCK,),
    "warpfem.kernels.fem": SPREAD_BLOCKS,
    "warpfem.kernels.integrate": SPREAD_BLOCKS,
    "warpfem.kernels.rigid": SPREAD_BLOCKS,
    "warpfem.kernels.skin": (WIDE_BLOCK,),
}
"""Each kernel module a simulation launches, with the block sizes its launches use on CUDA (the CPU runs
every launch in blocks of one thread, one variant per module). A launch with another block size would
compile a variant outside this table; ``tests/test_compile.py`` checks the table against the launches."""

LOAD_THREADS = 4
"""Modules compiled at once at most (Warp's own default; the compilers release Python's lock)."""


@dataclass(frozen=True)
class ModuleLoad:
    """One module variant loaded on one device.

    Attributes:
        module: The module's name.
        device: The device's alias.
        block_dim: Threads per block of the variant (1 on the CPU).
        compiled: Whether the kernel cache lacked it, so it was compiled.
        seconds: Wall time of its load (with others loading alongside).
    """

    module: str
    device: str
    block_dim: int
    compiled: bool
    seconds: float


def variants(modules: Mapping[str, Sequence[int]], device: wp.context.Device) -> list[tuple[str, int]]:
    """The (module, block size) pairs that ``modules`` launch on ``device``: one per module on the CPU."""
    if device.is_cpu:
        return [(name, 1) for name in modules]
    return [(name, int(dim)) for name, dims in modules.items() for dim in dims]


def _module(name: str) -> wp.context.Module:
    importlib.import_module(name)
    return wp.get_module(name)


def is_cached(name: str, device: wp.context.Device, block_dim: int) -> bool:
    """Whether the kernel cache holds module ``name``'s binary for ``device`` in blocks of ``block_dim``.

    Reads one file's existence, the path ``Module.load`` itself would read (a Warp-internal name; should it
    ever be missing, the module counts as cached and only the load's time tells).
    """
    module = _module(name)
    try:
        folder = os.path.join(wp.config.kernel_cache_dir, module.get_module_identifier(block_dim))
        return os.path.exists(os.path.join(folder, module._get_compile_output_name(device, block_dim=block_dim)))
    except (AttributeError, TypeError):
        return True


def load_modules(
    plan: Sequence[tuple[str | wp.context.Device, Mapping[str, Sequence[int]]]],
    notify: Callable[[str], None] | None = None,
) -> list[ModuleLoad]:
    """Load (compiling where the kernel cache lacks them) every variant of the modules planned per device.

    Args:
        plan: Pairs of a Warp device (or its name) and the modules to load there with their block sizes on
            CUDA, as :data:`STEP_MODULES`. A variant planned twice is loaded once.
        notify: Receives "compiling kernels (first run only): ..." before anything is compiled and the time it
            took after, one line each; nothing when every variant was cached.

    Returns:
        One entry per variant and device.
    """
    wp.init()
    jobs = []
    for where, modules in plan:
        device = wp.get_device(where)
        jobs += [(device, name, dim) for name, dim in variants(modules, device) if (device, name, dim) not in jobs]
    missing = [(d, name, dim) for d, name, dim in jobs if not is_cached(name, d, dim)]
    if missing and notify is not None:
        where = ", ".join(sorted({d.alias for d, _, _ in missing}))
        notify(f"compiling kernels (first run only): {len(missing)} Warp modules on {where}")
    clock = time.perf_counter()

    def load(group: list[tuple[wp.context.Device, str, int]]) -> list[ModuleLoad]:
        done = []
        for job in group:  # a module's variants one after another: only distinct modules load at once
            device, name, dim = job
            start = time.perf_counter()
            _module(name).load(device, block_dim=dim)
            done.append(ModuleLoad(name, device.alias, dim, job in missing, time.perf_counter() - start))
        return done

    groups: dict[tuple[str, str], list] = {}
    for job in jobs:
        groups.setdefault((job[0].alias, job[1]), []).append(job)
    with ThreadPoolExecutor(max_workers=min(LOAD_THREADS, os.cpu_count() or 1)) as pool:
        loads = [entry for group in pool.map(load, groups.values()) for entry in group]
    if missing and notify is not None:
        notify(f"compiled kernels in {time.perf_counter() - clock:.1f} s (kept in {wp.config.kernel_cache_dir})")
    return loads

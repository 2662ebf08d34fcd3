"""Build the simulation's CUDA kernels for a GPU on a machine without one, as Warp's kernel cache holds them.

    .venv/bin/python scripts/prebuild_cubins.py --out /tmp/cubins                 every step module, sm_90
    .venv/bin/python scripts/prebuild_cubins.py --out /tmp/cubins --modules collision --arch 80
    .venv/bin/python scripts/prebuild_cubins.py --out .warp-cache-gpu --prune    this tree's builds only

Warp names a module's binary by a hash of its code and options, the same here as on a GPU machine with the same
Warp, so copying the folders this writes into that machine's kernel cache (``wp.config.kernel_cache_dir``) makes
its first run load each module instead of compiling it: NVRTC takes minutes for the collision module, on the
device's time. Each module is built in every block size a step launches it with (``STEP_MODULES``). Warp writes
the binaries itself; where they go and what they are called are Warp internals (``Module.load``'s names), which
``tests/test_prebuild_cubins.py`` checks against the module's own loader.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from pathlib import Path


def targets(modules: list[str], arch: int) -> list[tuple[str, int, str, str]]:
    """(module, block size, cache folder, binary name) of each variant of ``warpfem.kernels.<module>``."""
    import warp as wp

    from warpfem.sim.modules import STEP_MODULES

    out = []
    for name in modules:
        full = f"warpfem.kernels.{name}"
        importlib.import_module(full)
        module = wp.get_module(full)
        for block in STEP_MODULES[full]:
            folder = module.get_module_identifier(block)
            binary = module._get_compile_output_name(None, output_arch=arch, use_ptx=False, block_dim=block)
            out.append((full, block, folder, binary))
    return out


def build(out: Path, modules: list[str], arch: int) -> list[Path]:
    """Write each variant's binary and metadata under ``out/<folder>/``; returns the binaries (built or present)."""
    import warp as wp

    written = []
    for full, block, folder, binary in targets(modules, arch):
        where = out / folder
        path = where / binary
        if not path.exists():
            clock = time.perf_counter()
            where.mkdir(parents=True, exist_ok=True)
            module = wp.get_module(full)
            module._compile(None, str(where), binary, arch, use_ptx=False, options=module.resolved_options[block])
            print(f"{full} in blocks of {block}: {folder} ({time.perf_counter() - clock:.0f} s)", flush=True)
        written.append(path)
    return written


def prune(out: Path, modules: list[str], kept: list[Path]) -> list[Path]:
    """Remove the folders under ``out`` of other builds of ``warpfem.kernels.<module>`` (older code, other options)
    than ``kept``'s, so that a cache carried to the GPU machine holds this tree's modules only; returns them."""
    import shutil

    keep = {path.parent.name for path in kept}
    stale = [
        folder
        for name in modules
        for folder in out.glob(f"wp_warpfem.kernels.{name}_*")
        if folder.is_dir() and folder.name not in keep
    ]
    for folder in stale:
        shutil.rmtree(folder)
    return stale


def main(argv: list[str] | None = None) -> int:
    import warp as wp

    from warpfem.sim.modules import STEP_MODULES

    known = sorted(name.rpartition(".")[2] for name in STEP_MODULES)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="folder to write the cache's module folders in")
    parser.add_argument("--modules", default=",".join(known), help=f"comma-separated, of: {', '.join(known)}")
    parser.add_argument("--arch", type=int, default=90, help="the GPU's compute capability, e.g. 80 or 90")
    parser.add_argument(
        "--prune", action="store_true", help="remove the folders of the modules' other builds from --out"
    )
    args = parser.parse_args(argv)
    if not 50 <= args.arch <= 130:
        parser.error(f"--arch must be an SM version such as 80 or 90, got {args.arch}")
    modules = [m for m in args.modules.split(",") if m]
    unknown = [m for m in modules if m not in known]
    if unknown:
        print(f"prebuild_cubins: no step module {unknown[0]!r} (have: {', '.join(known)})", file=sys.stderr)
        return 2
    wp.config.quiet = True
    wp.init()
    try:
        built = build(args.out, modules, args.arch)
    except Exception as err:  # Warp's NVRTC build raises a bare Exception
        print(f"prebuild_cubins: NVRTC could not build for sm_{args.arch}: {err}", file=sys.stderr)
        return 2
    if args.prune:
        for folder in prune(args.out, modules, built):
            print(f"removed {folder.name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

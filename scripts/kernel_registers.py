"""Registers a thread and spills of warpfem's CUDA kernels, without a GPU: Warp writes each module's PTX, ptxas counts.

    .venv/bin/python scripts/kernel_registers.py                      every module of warpfem.kernels
    .venv/bin/python scripts/kernel_registers.py collision --match detect --arch 90 --block 32

Registers bound how many warps a multiprocessor keeps resident, which is what hides a kernel's loads: a change
that adds live values to a hot loop can cost more than its arithmetic (docs/performance.md). This compares a
change's counts with the tree before it, on a machine with no GPU. Needs ``ptxas`` (the CUDA toolkit) on PATH;
Warp's own NVRTC writes the PTX. Where the PTX's ISA version is newer than this ptxas reads, it is lowered to
the newest ptxas names (the kernels use no instruction added since). Forward kernels only. For sm_80 and sm_90
it also gives the warps an SM keeps resident at ``--block`` threads a block as the registers allow (shared
memory aside): one register more can cost a warp, as 152 to 153 does at blocks of 32.
"""

from __future__ import annotations

import argparse
import importlib
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NEWEST = re.compile(r"current version is '(\d+\.\d+)'")


def ptx_of(module: str, arch: int, work: Path) -> str:
    """The PTX text of ``warpfem.kernels.<module>`` for ``sm_<arch>``."""
    import warp as wp

    wp.config.quiet = True
    wp.init()
    try:
        paths = wp.compile_aot_module(importlib.import_module(f"warpfem.kernels.{module}"), arch=arch,
                                      module_dir=work, use_ptx=True)  # fmt: skip
    except Exception as err:  # Warp's NVRTC build raises a bare Exception
        raise RuntimeError(f"NVRTC could not build it for sm_{arch}: {err}") from None
    return Path(paths[0]).read_bytes().replace(b"\x00", b"").decode()


def assemble(ptx: str, arch: int, work: Path) -> str:
    """ptxas's verbose report on ``ptx``, its ISA version lowered once if this ptxas asks for it."""
    path = work / "module.ptx"
    for _ in range(2):
        path.write_text(ptx)
        run = subprocess.run(["ptxas", f"-arch=sm_{arch}", "-v", str(path), "-o", "/dev/null"],
                             capture_output=True, text=True)  # fmt: skip
        newest = NEWEST.search(run.stderr)
        if run.returncode == 0 or newest is None:
            break
        ptx = re.sub(r"^\.version \d+\.\d+", f".version {newest.group(1)}", ptx, count=1, flags=re.M)
    if run.returncode != 0:
        raise RuntimeError(f"ptxas could not assemble it: {run.stderr.strip().splitlines()[-1]}")
    return run.stderr


SM_LIMITS = {80: (65536, 64, 32), 90: (65536, 64, 32)}
"""Per SM architecture: registers, resident warps and resident blocks an SM holds (CUDA's occupancy tables)."""

REGISTER_UNIT = 256
"""Registers are given to a warp in multiples of this (sm_80, sm_90)."""


def resident_warps(registers: int, block: int, arch: int) -> int | None:
    """Warps an SM of ``sm_<arch>`` keeps resident at ``registers`` a thread and ``block`` threads a block, as the
    register file, the warp and the block limits allow (None for an architecture not in :data:`SM_LIMITS`)."""
    if arch not in SM_LIMITS:
        return None
    file, most_warps, most_blocks = SM_LIMITS[arch]
    warps = -(-block // 32)
    per_warp = -(-registers * 32 // REGISTER_UNIT) * REGISTER_UNIT
    blocks = min(file // (per_warp * warps), most_blocks, most_warps // warps)
    return blocks * warps


def usage(report: str) -> dict[str, tuple[int, int]]:
    """Per forward kernel (Warp's hash suffix dropped): registers a thread and bytes spilled (stores)."""
    found: dict[str, tuple[int, int]] = {}
    name, spill = None, 0
    for line in report.splitlines():
        entry = re.search(r"Compiling entry function '(\w+)_[0-9a-f]+_cuda_kernel_forward'", line)
        if entry or "Compiling entry function" in line:
            name, spill = (entry.group(1) if entry else None), 0
        stores = re.search(r"(\d+) bytes spill stores", line)
        if stores:
            spill = int(stores.group(1))
        used = re.search(r"Used (\d+) registers", line)
        if used and name:
            found[name] = (int(used.group(1)), spill)
    return found


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("modules", nargs="*", help="modules of warpfem.kernels (default: all)")
    parser.add_argument("--arch", type=int, default=90, help="SM architecture (default 90: H100, H200)")
    parser.add_argument("--match", default="", help="only kernels whose name contains this")
    parser.add_argument("--block", type=int, default=32, help="threads a block for the warps column (default 32)")
    args = parser.parse_args(argv)
    if not 50 <= args.arch <= 130:
        parser.error(f"--arch must be an SM version such as 80 or 90, got {args.arch}")
    if not 1 <= args.block <= 1024:
        parser.error(f"--block must be 1 to 1024 threads, got {args.block}")
    known = sorted(p.stem for p in (ROOT / "kernels").glob("*.py") if p.stem != "__init__")
    for module in args.modules:
        if module not in known:
            print(f"kernel_registers: no module {module!r} in kernels/ (have: {', '.join(known)})", file=sys.stderr)
            return 2
    if shutil.which("ptxas") is None:
        print("kernel_registers: ptxas not found on PATH (it comes with the CUDA toolkit)", file=sys.stderr)
        return 2
    sys.path.insert(0, str(ROOT))
    for module in args.modules or known:
        with tempfile.TemporaryDirectory() as tmp:
            try:
                counts = usage(assemble(ptx_of(module, args.arch, Path(tmp)), args.arch, Path(tmp)))
            except RuntimeError as err:
                print(f"kernel_registers: {module}: {err}", file=sys.stderr)
                return 1
        for name, (registers, spill) in sorted(counts.items()):
            if args.match in name:
                warps = resident_warps(registers, args.block, args.arch)
                shown = f"  {warps:3d} warps an SM at blocks of {args.block}" if warps is not None else ""
                print(f"{module:12s} {name:40s} {registers:4d} registers  {spill:5d} bytes spilled{shown}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

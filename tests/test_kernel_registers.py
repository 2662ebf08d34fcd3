"""scripts/kernel_registers.py: registers a thread of each CUDA kernel, counted by ptxas on Warp's PTX (no GPU)."""

import re
import shutil
import sys
from pathlib import Path

import pytest
import warp as wp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))

import kernel_registers  # noqa: E402


@pytest.mark.skipif(shutil.which("ptxas") is None, reason="ptxas (the CUDA toolkit) is not on PATH")
def test_every_kernel_of_a_module_gets_its_register_count(capsys):
    """The kernels listed are exactly those Warp registers in the module, each at 1-255 registers (the most a
    thread can address on sm_90)."""
    import warpfem.kernels.approach as approach

    assert kernel_registers.main(["approach"]) == 0
    rows = [line.split() for line in capsys.readouterr().out.splitlines() if line.startswith("approach ")]
    counts = {row[1]: int(row[2]) for row in rows}
    assert set(counts) == set(wp.get_module(approach.__name__).kernels)
    assert all(1 <= n <= 255 for n in counts.values()), counts


def test_an_unknown_module_is_a_one_line_error(capsys):
    assert kernel_registers.main(["no_such_stage"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and re.match(r"kernel_registers: no module 'no_such_stage' in kernels/", err[0])


@pytest.mark.parametrize("arch", ["1", "900", "ninety"])
def test_a_bad_arch_is_a_one_line_error(capsys, arch):
    with pytest.raises(SystemExit) as stop:
        kernel_registers.main(["approach", "--arch", arch])
    assert stop.value.code == 2
    err = [line for line in capsys.readouterr().err.splitlines() if "error:" in line]
    assert len(err) == 1 and "--arch" in err[0]


@pytest.mark.parametrize(
    "registers, block, warps",
    [(32, 256, 64), (64, 256, 32), (128, 256, 16), (255, 256, 8), (152, 32, 13), (153, 32, 12), (40, 32, 32)],
)
def test_resident_warps_follow_cudas_occupancy_tables(registers, block, warps):
    """The warps an H100/H200 SM keeps at a register count, as CUDA's occupancy calculator gives them (65,536
    registers given out 256 to a warp, at most 64 warps and 32 blocks an SM): 153 registers cost blocks of one
    warp a warp against 152."""
    assert kernel_registers.resident_warps(registers, block, 90) == warps


def test_a_bad_block_is_a_one_line_error(capsys):
    with pytest.raises(SystemExit) as stop:
        kernel_registers.main(["approach", "--block", "0"])
    assert stop.value.code == 2
    err = [line for line in capsys.readouterr().err.splitlines() if "error:" in line]
    assert len(err) == 1 and "--block" in err[0]

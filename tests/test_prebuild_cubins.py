"""scripts/prebuild_cubins.py: a step module's CUDA binaries built without a GPU, where Warp's loader looks."""

import re
import sys
from pathlib import Path

import pytest
import warp as wp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))

import prebuild_cubins  # noqa: E402


def test_a_module_is_built_in_every_block_size_under_the_names_warps_own_build_gives(tmp_path, monkeypatch):
    """The binary of the module's default block size is named and placed as Warp's public ahead-of-time build
    names it, and every block size a step launches gets a binary and its metadata beside it (a small module,
    given two block sizes here)."""
    import warpfem.kernels.approach as approach

    from warpfem.sim.launch import SPREAD_BLOCKS, WIDE_BLOCK
    from warpfem.sim.modules import STEP_MODULES

    monkeypatch.setitem(STEP_MODULES, approach.__name__, SPREAD_BLOCKS)
    stale, other = tmp_path / "cache" / f"wp_{approach.__name__}_0000000", tmp_path / "cache" / "wp_elsewhere_0000000"
    for folder in (stale, other):  # an older build of the module, and a module not named
        folder.mkdir(parents=True)
    assert prebuild_cubins.main(["--out", str(tmp_path / "cache"), "--modules", "approach", "--prune"]) == 0
    assert not stale.exists() and other.exists()
    other.rmdir()
    module = wp.get_module(approach.__name__)
    reference = wp.compile_aot_module(module, arch=90, module_dir=tmp_path / "aot", use_ptx=False)[0]
    built = sorted((tmp_path / "cache").glob("*/*.sm90.cubin"))
    assert len(built) == len(SPREAD_BLOCKS) == len({p.parent for p in built})
    assert module.options["block_dim"] == WIDE_BLOCK and reference.name in [p.name for p in built]
    for path in built:
        assert path.parent.name == path.name.partition(".sm90")[0] and path.stat().st_size > 0
        assert path.with_name(path.name.replace(".sm90.cubin", ".meta")).exists()


def test_an_unknown_module_is_a_one_line_error(tmp_path, capsys):
    assert prebuild_cubins.main(["--out", str(tmp_path), "--modules", "no_such_stage"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and re.match(r"prebuild_cubins: no step module 'no_such_stage' \(have: ", err[0])
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("arch", ["1", "900", "ninety"])
def test_a_bad_arch_is_refused(tmp_path, arch):
    with pytest.raises(SystemExit) as stop:
        prebuild_cubins.main(["--out", str(tmp_path), "--arch", arch])
    assert stop.value.code == 2

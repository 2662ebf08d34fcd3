"""The quality presets through the whole pipeline: a dense triangulated cantilever prepared with only
``[solver] quality`` set, held still at x <= 0 by a handle, damped to rest under gravity; its dense tip sag
against NGSolve's p-converged Saint Venant-Kirchhoff answer (tests/test_reference.py)."""

import pytest

from warpfem.study.presets import measure, write_beam
from warpfem.study.reference import Cantilever

pytestmark = pytest.mark.slow

CONVERGED_SAG = 0.1447865891312432
"""NGSolve's converged nonlinear sag of the default :class:`Cantilever` (m)."""


@pytest.fixture(scope="module")
def default_point(tmp_path_factory):
    work = tmp_path_factory.mktemp("presets")
    return measure("default", write_beam(work / "beam.obj", Cantilever()), CONVERGED_SAG, work / "cache")


def test_default_preset_sags_within_15_percent(default_point):
    # measured: -13.6 % at 3,796 tets (sized 4 tets across); -27 % when presets sized by the bounding box
    assert -0.15 < default_point.sag_error < 0.0
    assert 3000 < default_point.tets < 6000


@pytest.mark.xfail(
    strict=True,
    reason="linear tets lock in bending: default sags 13.6 % short at 3,796 tets; 5 % takes about 8 tets "
    "across (31,020 tets, -3.5 %), which would make the scans' default 20x as many tets",
)
def test_default_preset_sags_within_5_percent(default_point):
    assert abs(default_point.sag_error) < 0.05


@pytest.mark.xfail(
    strict=True,
    reason="linear tets lock in bending: high's 20,879 tets (8 across, 3,000 faces) sag 4.7 % short; 2 % takes "
    "about 13 across (11 across with 11,688 faces: 54,561 tets, -2.7 %)",
)
def test_high_preset_tets_sag_within_2_percent(tmp_path):
    """NGSolve P1 on the tets the high preset makes: warpfem's settled sag equals it to 0.1 % (measured at
    default and at 8 across; the high run itself takes minutes on the CPU, see scripts/preset_beam.py)."""
    from warpfem.build import prepare_scene
    from warpfem.study.presets import beam_scene
    from warpfem.study.reference import sag_on_tets

    beam = Cantilever()
    body = prepare_scene(beam_scene(write_beam(tmp_path / "beam.obj", beam), "high", beam), None)[0]
    sag = sag_on_tets(beam, body.tet_vertices, body.tets, nonlinear=True)
    assert abs(sag / CONVERGED_SAG - 1.0) < 0.02


CONVERGED_SAG_049 = 0.14260
"""NGSolve's nonlinear sag of the cantilever at nu 0.49, order 6 on a Netgen mesh (m; orders 4, 5, 6: 142.02,
142.43, 142.60 mm; near-incompressible elements need the high order)."""


@pytest.mark.xfail(
    strict=True,
    reason="volumetric locking: at nu 0.49 the default preset's linear tets sag 40 % short (85 mm of 142.6 mm), "
    "against 13.6 % at nu 0.3; 8 across (31,020 tets, NGSolve P1) 13.6 % short, against 3.5 %",
)
def test_near_incompressible_default_does_not_lock(tmp_path):
    beam = Cantilever(poisson=0.49)
    point = measure("default", write_beam(tmp_path / "beam.obj", beam), CONVERGED_SAG_049, tmp_path / "cache", beam)
    assert point.sag_error > -0.15  # no worse than the same preset at nu 0.3

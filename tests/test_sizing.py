"""Tet size from the body's thickness: the thickness against analytic values, the size against its rule, and
the accuracy it buys against NGSolve's converged nonlinear cantilever on the very tets the pipeline made."""

import numpy as np
import pytest
import trimesh

from warpfem.errors import InputError
from warpfem.prep.pipeline import prepare
from warpfem.prep.sizing import FACES_PER_AREA, TETS_PER_VOLUME, local_thickness, size_from_thickness
from warpfem.study.presets import beam_surface
from warpfem.study.reference import Cantilever

BEAM = Cantilever()
CONVERGED_SAG = 0.1447865891312432
"""NGSolve's p-converged Saint Venant-Kirchhoff sag of BEAM (m), tests/test_reference.py."""


@pytest.fixture(scope="module")
def beam_file(tmp_path_factory):
    vertices, faces = beam_surface(BEAM)
    path = tmp_path_factory.mktemp("beam") / "beam.obj"
    trimesh.Trimesh(vertices, faces, process=False).export(path)
    return path


def test_thickness_of_a_beam_is_its_side():
    vertices, faces = beam_surface(BEAM)
    thickness = local_thickness(vertices, faces)
    assert len(thickness) > 1000
    # a vertex on a side face sees the opposite face 0.1 m away; those on edges and ends see farther
    assert np.percentile(thickness, 10) == pytest.approx(0.1, rel=1e-4)
    assert thickness.min() == pytest.approx(0.1, rel=1e-4)


def test_thickness_of_a_sphere_is_its_diameter():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.3)
    thickness = local_thickness(np.asarray(sphere.vertices), np.asarray(sphere.faces))
    np.testing.assert_allclose(thickness, 0.6, rtol=5e-3)  # the chord through the centre, on a faceted sphere


def test_size_puts_tets_across_the_thickness_within_the_budget():
    vertices, faces = beam_surface(BEAM)
    free = size_from_thickness(vertices, faces, across=4, max_tets=10**6, min_faces=100, max_h=1.0)
    assert free.maxh == pytest.approx(0.025, rel=1e-3) and not free.capped
    area = 2 * (BEAM.length * BEAM.height + BEAM.length * BEAM.width + BEAM.height * BEAM.width)
    assert free.faces == round(FACES_PER_AREA * area / 0.025**2)
    capped = size_from_thickness(vertices, faces, across=4, max_tets=500, min_faces=100, max_h=1.0)
    assert capped.capped and capped.maxh == pytest.approx((TETS_PER_VOLUME * 0.01 / 500) ** (1 / 3), rel=1e-3)
    assert size_from_thickness(vertices, faces, across=4, max_tets=10**6, min_faces=100, max_h=0.02).maxh == 0.02
    assert size_from_thickness(vertices, faces, across=1, max_tets=10**6, min_faces=900, max_h=1.0).faces == 900
    with pytest.raises(InputError, match="must be positive"):
        size_from_thickness(vertices, faces, across=0, max_tets=10, min_faces=100, max_h=1.0)


def test_sized_beam_sags_twice_as_close_to_ngsolve(beam_file):
    from warpfem.study.reference import sag_on_tets

    errors = {}
    for across in (0.0, 4.0):
        body = prepare(beam_file, faces=1000, maxh=0.2, cache_dir=None, across=across)
        sag = sag_on_tets(BEAM, body.tet_vertices, body.tets, nonlinear=True)
        errors[across] = sag / CONVERGED_SAG - 1.0
    # measured: -27.9 % sized by the bounding box (1,537 tets), -13.6 % at 4 across (3,796 tets)
    assert errors[0.0] < -0.25
    assert -0.16 < errors[4.0] < -0.10


def test_tet_budget_bounds_a_thin_featured_body():
    body = prepare("builtin:bunny", faces=1000, maxh=0.2, cache_dir=None, across=8, max_tets=3000)
    assert body.stats["sizing_capped"] == 1
    assert 1500 < body.stats["tets"] < 1.3 * 3000
    diag = np.linalg.norm(np.ptp(body.dense_vertices, axis=0))
    assert body.stats["thickness"] == pytest.approx(body.stats["thickness_relative"] * diag)


def test_a_body_over_its_tet_budget_is_sized_again(asset):
    """Netgen fills the armadillo's cage more densely than the sizing's volume estimate, so at 2 tets across and
    a budget of 3,000 (the default preset) the first sizing overshoots; sized once more, it ends within it."""
    body = prepare(asset("armadillo.off"), faces=1000, maxh=0.2, cache_dir=None, across=2, max_tets=3000)
    assert body.stats["sized_twice"] == 1
    assert 1000 < body.stats["tets"] <= 1.25 * 3000
    assert body.stats["max_tets"] == 3000


def test_cache_keeps_sized_and_unsized_apart(beam_file, tmp_path):
    plain = prepare(beam_file, faces=1000, cache_dir=tmp_path)
    sized = prepare(beam_file, faces=1000, cache_dir=tmp_path, across=4)
    assert sized.stats["cache"] == "miss" and sized.stats["tets"] != plain.stats["tets"]
    again = prepare(beam_file, faces=1000, cache_dir=tmp_path, across=4)
    assert again.stats["cache"] == "hit" and again.stats["tets"] == sized.stats["tets"]
    other = prepare(beam_file, faces=1000, cache_dir=tmp_path, across=4, max_tets=2000)
    assert other.stats["cache"] == "miss"


@pytest.mark.parametrize(
    ("across", "max_tets", "message"),
    [(-1.0, 100, "across must be >= 0"), (float("nan"), 100, "across must be"), (4.0, 0, "max_tets >= 1")],
)
def test_bad_sizing_is_one_line(beam_file, across, max_tets, message):
    with pytest.raises(InputError, match=message):
        prepare(beam_file, faces=1000, cache_dir=None, across=across, max_tets=max_tets)


def test_quality_preset_fills_the_sizing_keys():
    from warpfem.scene import PRESETS, Scene

    obj = {"name": "b", "mesh": "builtin:bunny"}
    scene = Scene.from_dict({"solver": {"quality": "high"}, "object": [obj, obj | {"name": "c", "tets_across": 2}]})
    assert scene.objects[0].tets_across == PRESETS["high"]["tets_across"] > 0
    assert scene.objects[0].max_tets == PRESETS["high"]["max_tets"]
    assert scene.objects[1].tets_across == 2  # the file wins
    assert Scene.from_dict({"object": [obj]}).objects[0].tets_across == 0.0  # no preset: sized as before


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [("tets_across", -1.0, r"tets_across must be >= 0 and <= 64, got -1"), ("max_tets", 50, r"max_tets must be in")],
)
def test_bad_sizing_key_is_one_line(key, value, message):
    from warpfem.scene import Scene

    with pytest.raises(InputError, match=r"object\[0\] 'b': " + message):
        Scene.from_dict({"object": [{"name": "b", "mesh": "builtin:bunny", key: value}]})

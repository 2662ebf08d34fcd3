"""NGSolve references for the cantilever, and warpfem's corotational FEM against them."""

import numpy as np
import pytest

from warpfem.build import add_body
from warpfem.errors import InputError
from warpfem.prep.shapes import box_tet_mesh
from warpfem.sim.model import ModelBuilder
from warpfem.sim.solver import Solver
from warpfem.study.reference import Cantilever, converged_sag, sag_on_tets


def test_converged_linear_sag_matches_euler_bernoulli():
    beam = Cantilever(young=1e7, poisson=0.0)  # slender (L/h = 10): shear adds ~0.8 %
    study = converged_sag(beam, rtol=2e-3)
    assert study.change < 2e-3
    assert list(study.sags) == sorted(study.sags)  # p-refinement softens monotonically
    assert study.sag == pytest.approx(beam.euler_bernoulli_sag(), rel=0.02)


def test_large_deflection_is_geometrically_nonlinear():
    beam = Cantilever(young=2e6)
    linear = converged_sag(beam, orders=(2, 3)).sag
    nonlinear = converged_sag(beam, nonlinear=True, orders=(2, 3), load_steps=8).sag
    assert linear == pytest.approx(beam.euler_bernoulli_sag(), rel=0.02)
    assert nonlinear < 0.8 * linear  # the bent beam carries its weight partly by stretching


def _warp_sag(device, beam, vertices, tets, steps, dt, **solver):
    b = ModelBuilder()
    add_body(b, "beam", vertices, tets, beam.young, beam.poisson, beam.density, pinned=vertices[:, 0] < 1e-9)
    model = b.finalize(device)
    solver = Solver(model, gravity=(0, -beam.gravity, 0), ground=None, cg_iterations=3000, cg_tolerance=1e-6, **solver)
    s0, s1 = model.state(), model.state()
    tip = np.isclose(vertices[:, 0], beam.length)
    sags = []
    for _ in range(steps):  # backward Euler with a long step relaxes to the static equilibrium
        solver.step(s0, s1, dt)
        s0, s1 = s1, s0
        sags.append(vertices[tip, 1].mean() - s0.x.numpy()[tip, 1].mean())
    return np.array(sags)


def test_small_deflection_matches_ngsolve_p1_on_the_same_tets(device):
    beam = Cantilever(young=1e7)
    V, T = box_tet_mesh((0, 0, 0), (1.0, 0.1, 0.1), (20, 2, 2))
    linear, nonlinear = sag_on_tets(beam, V, T), sag_on_tets(beam, V, T, nonlinear=True)
    # without rotation updates the first long step is one linear solve from the rest shape: linear FEM on the
    # same tets; with them, each step re-linearised about its end: the nonlinear answer from the first step
    assert _warp_sag(device, beam, V, T, 1, 100.0, rotation_updates=0)[0] == pytest.approx(linear, rel=2e-3)
    sags = _warp_sag(device, beam, V, T, 6, 100.0)
    assert abs(sags[0] - nonlinear) < 0.25 * abs(sags[0] - linear)
    assert sags[-1] == pytest.approx(nonlinear, rel=3e-3)


def test_corotational_follows_the_nonlinear_answer_at_large_deflection(device):
    beam = Cantilever(young=1e6)  # linear P1 sag 0.75 L on this mesh
    V, T = box_tet_mesh((0, 0, 0), (1.0, 0.1, 0.1), (20, 2, 2))
    linear = sag_on_tets(beam, V, T)
    nonlinear = sag_on_tets(beam, V, T, nonlinear=True, load_steps=8)
    corotational = _warp_sag(device, beam, V, T, 16, 100.0)[-8:].mean()  # it rocks by ~0.5 % about equilibrium
    assert abs(corotational - nonlinear) < 0.02 * nonlinear
    assert abs(corotational - linear) > 0.2 * linear


def test_bad_beam_is_input_error():
    with pytest.raises(InputError, match="poisson"):
        Cantilever(poisson=0.5)
    with pytest.raises(InputError, match="young"):
        Cantilever(young=-1.0)

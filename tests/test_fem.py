"""The corotational FEM kernel against analytic linear elasticity."""

import numpy as np
import pytest
import warp as wp

from warpfem.build import add_body
from warpfem.prep.shapes import box_tet_mesh
from warpfem.sim import fem
from warpfem.sim.model import ModelBuilder, lame

E, NU = 1.0e6, 0.3


def _model(vertices, tets, device, young=E, poisson=NU):
    b = ModelBuilder()
    add_body(b, "b", vertices, tets, young, poisson, 1000.0)
    return b.finalize(device)


def _evaluate(model, x, dt=1.0):
    """Elastic forces (n,3), dense stiffness (3n,3n) scaled by dt^2, rotations (q,3,3)."""
    n = model.vertex_count
    force = wp.zeros(n, dtype=wp.vec3, device=model.device)
    matrix = wp.zeros(model.nnz_blocks, dtype=wp.mat33, device=model.device)
    rot = wp.zeros(model.tet_count, dtype=wp.mat33, device=model.device)
    xw = wp.array(np.asarray(x, np.float32), dtype=wp.vec3, device=model.device)
    fem.elastic_forces_and_stiffness(model, xw, dt, rot, force, matrix)
    dense = np.zeros((3 * n, 3 * n))
    rs, cols, vals = model.row_start.numpy(), model.cols.numpy(), matrix.numpy()
    for i in range(n):  # the upper triangle is stored; the lower is its transpose
        for s in range(rs[i], rs[i + 1]):
            dense[3 * i : 3 * i + 3, 3 * cols[s] : 3 * cols[s] + 3] = vals[s]
            dense[3 * cols[s] : 3 * cols[s] + 3, 3 * i : 3 * i + 3] = vals[s].T
    return force.numpy(), dense, rot.numpy()


def _random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


def test_rigid_motion_has_no_elastic_force(device):
    rng = np.random.default_rng(0)
    V, T = box_tet_mesh((0, 0, 0), (0.3, 0.2, 0.1), (3, 2, 2))
    model = _model(V, T, device)
    for _ in range(3):
        R = _random_rotation(rng)
        x = V @ R.T + rng.normal(size=3)
        f, _, rot = _evaluate(model, x)
        scale = E * 0.1**2  # N: stress times an element face
        assert np.abs(f).max() < 1e-4 * scale
        np.testing.assert_allclose(rot, np.broadcast_to(R, rot.shape), atol=1e-4)


def test_constant_strain_patch(device):
    """An affine small deformation: interior nodes in equilibrium, face resultant = analytic traction."""
    lo, hi = np.zeros(3), np.array([0.3, 0.2, 0.2])
    V, T = box_tet_mesh(lo, hi, (3, 2, 2))
    model = _model(V, T, device)
    eps = 1e-3 * np.array([[1.0, 0.3, -0.2], [0.3, -0.5, 0.4], [-0.2, 0.4, 0.8]])  # symmetric: R = I
    f, _, _ = _evaluate(model, V @ (np.eye(3) + eps).T)
    mu, lam = lame(E, NU)
    sigma = 2 * mu * eps + lam * np.trace(eps) * np.eye(3)
    on_boundary = (np.isclose(V, lo) | np.isclose(V, hi)).any(axis=1)
    resultant = np.abs(sigma).max() * 0.04
    assert np.abs(f[~on_boundary]).max() < 1e-3 * resultant
    face = np.isclose(V[:, 0], hi[0])
    area = (hi[1] - lo[1]) * (hi[2] - lo[2])
    np.testing.assert_allclose(f[face].sum(axis=0), -sigma[:, 0] * area, rtol=2e-3, atol=1e-3 * resultant)


def test_element_stiffness_spd_with_six_rigid_modes(device):
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0.2, 0.9, 0], [0.3, 0.3, 0.8]])
    model = _model(V, np.array([[0, 1, 2, 3]]), device)
    _, K, _ = _evaluate(model, V)
    assert np.abs(K - K.T).max() < 1e-5 * np.abs(K).max()
    w = np.linalg.eigvalsh(0.5 * (K + K.T))
    assert w.min() > -1e-5 * w.max()
    assert (np.abs(w) < 1e-5 * w.max()).sum() == 6
    assert w[6] > 1e-3 * w.max()
    c = V.mean(axis=0)
    for axis in np.eye(3):
        translation = np.tile(axis, 4)
        rotation = np.cross(axis, V - c).ravel()
        for mode in (translation, rotation):
            assert np.linalg.norm(K @ mode) < 1e-5 * np.abs(w).max() * np.linalg.norm(mode)


def test_stiffness_is_the_force_jacobian_at_rest(device):
    rng = np.random.default_rng(1)
    V, T = box_tet_mesh((0, 0, 0), (0.2, 0.2, 0.2), (1, 1, 1))
    model = _model(V, T, device)
    _, K, _ = _evaluate(model, V)
    du = 1e-4 * rng.normal(size=V.shape)
    f, _, _ = _evaluate(model, V + du)
    np.testing.assert_allclose(f.ravel(), -K @ du.ravel(), atol=2e-2 * np.abs(K @ du.ravel()).max())


@pytest.mark.parametrize("kind", ["flat", "inverted"])
def test_rotation_is_proper_for_degenerate_tets(device, kind):
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    model = _model(V, np.array([[0, 1, 2, 3]]), device)
    x = V.copy()
    x[3, 2] = 0.0 if kind == "flat" else -0.5
    f, _, rot = _evaluate(model, x)
    R = rot[0]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-5)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-5)
    assert np.isfinite(f).all()
    assert f[3, 2] > 0  # the squashed corner is pushed back up


def test_rotation_watch_measures_how_far_tets_turned(device):
    from warpfem.sim.fem import RotationWatch

    V, T = box_tet_mesh((0, 0, 0), (0.2, 0.2, 0.2), (2, 2, 2))
    model = _model(V, T, device)
    n = model.vertex_count
    force = wp.zeros(n, dtype=wp.vec3, device=device)
    matrix = wp.zeros(model.nnz_blocks, dtype=wp.mat33, device=device)
    rotation = wp.zeros(model.tet_count, dtype=wp.mat33, device=device)
    fem.elastic_forces_and_stiffness(model, model.rest_x, 1.0, rotation, force, matrix)
    watch = RotationWatch(model, rotation)
    angle = 0.1
    c, s = np.cos(angle), np.sin(angle)
    turned = V @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T
    fem.elastic_forces_and_stiffness(
        model, wp.array(turned.astype(np.float32), dtype=wp.vec3, device=device), 1.0, rotation, force, matrix
    )
    assert watch.turned()[0] == pytest.approx(angle, abs=1e-3)
    assert watch.turned()[0] == pytest.approx(0.0, abs=1e-3)  # nothing turned since


def _numpy_turns(x, V, T, rotations):
    """Each tet's turn (rad) at ``x`` from ``rotations``: the polar factor by NumPy's SVD."""
    d = V[T[:, 1:]] - V[T[:, :1]]
    F = np.transpose(x[T[:, 1:]] - x[T[:, :1]], (0, 2, 1)) @ np.linalg.inv(np.transpose(d, (0, 2, 1)))
    u, _, vt = np.linalg.svd(F)
    R = u @ vt
    turn = R @ np.transpose(rotations, (0, 2, 1))
    return np.arccos(np.clip((np.trace(turn, axis1=1, axis2=2) - 1) / 2, -1, 1)), R, np.abs(np.linalg.det(d)) / 6


@pytest.mark.parametrize("twist, start", [(0.0, 0.8), (0.015, 0.8), (0.05, 0.8), (0.5, 0.8), (0.03, 0.95)])
def test_rotation_updates_re_linearise_bodies_that_turned_enough(device, twist, start):
    """Two bars, one twisted about its long axis by ``twist`` rad from ``start`` to its end only (a turn that
    grows along it), the other turned rigidly by 0.9 or 1.2 times the tolerance. A body is re-linearised where
    the volume average of its tets' turn^4 exceeds the tolerance^4 or one of its tets turned past twice the
    tolerance, and then only its tets past the tolerance. NumPy's polar factors and volumes give the expected
    tets: the twist of 0.015 turns some tets past the tolerance but too few, and the one of 0.03 at its end too
    few on average but past twice it."""
    from warpfem.sim.cg import CGSolver

    tol = 0.01
    V, T = box_tet_mesh((0, 0, 0), (1.0, 0.1, 0.1), (20, 2, 2))
    b = ModelBuilder()
    add_body(b, "twisted", V, T, E, NU, 1000.0)
    add_body(b, "turned", V + [0, 1, 0], T, E, NU, 1000.0)
    model = b.finalize(device)
    angle = np.clip((V[:, 0] - start) / (1 - start), 0, 1) * twist  # about the bar's axis
    c, s = np.cos(angle), np.sin(angle)
    y, z = V[:, 1] - 0.05, V[:, 2] - 0.05
    twisted = np.stack([V[:, 0], 0.05 + c * y - s * z, 0.05 + s * y + c * z], 1)
    rigid = (0.9 if twist < 0.05 else 1.2) * tol
    c, s = np.cos(rigid), np.sin(rigid)
    turned = (V - 0.5) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + 0.5 + [0, 1, 0]
    x = np.concatenate([twisted, turned])
    cg = CGSolver(model.row_start, model.cols, model.free, 10, device)
    check = fem.TurnCheck(model, True)
    identity = np.tile(np.eye(3, dtype=np.float32), (model.tet_count, 1, 1))
    rotation = wp.array(identity, dtype=wp.mat33, device=device)
    body_turn = wp.zeros(2, dtype=wp.vec3, device=device)
    changed = wp.zeros(1, dtype=wp.int32, device=device)
    body_changed = wp.zeros(2, dtype=wp.int32, device=device)
    points = wp.array(x.astype(np.float32), dtype=wp.vec3, device=device)
    check.look(points, tol, cg, rotation, body_turn, changed, body_changed)

    expected = identity.astype(float).copy()
    enough = []
    for k, pos in enumerate([twisted, turned]):
        turn, R, vol = _numpy_turns(pos, V + ([0, 1, 0] if k else 0), T, identity[: len(T)].astype(float))
        enough.append(np.sum(vol * turn**4) / np.sum(vol) > tol**4 or turn.max() > 2 * tol)
        if enough[-1]:
            rows = expected[k * len(T) : (k + 1) * len(T)]
            rows[turn > tol] = R[turn > tol]
    np.testing.assert_allclose(rotation.numpy(), expected, atol=2e-4)
    assert changed.numpy()[0] == int(np.abs(expected - identity).max() > 0)
    n = len(T)
    replaced = [int(np.abs(expected[k * n : (k + 1) * n] - identity[:n]).max() > 0) for k in range(2)]
    assert body_changed.numpy().tolist() == replaced
    assert enough == [twist not in (0.0, 0.015), twist >= 0.05]
    if twist == 0.015:  # some of its tets turned past the tolerance, too few: left as they were
        turn = _numpy_turns(twisted, V, T, identity[: len(T)].astype(float))[0]
        assert turn.max() > tol and np.allclose(rotation.numpy()[: len(T)], identity[: len(T)], atol=1e-6)

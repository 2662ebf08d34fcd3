"""The collider's depth below the visible surface, against libigl's signed distance on the dense mesh moved."""

import numpy as np
import warp as wp
from warpfem.kernels.collision import depth_above
from warpfem.kernels.surface import VisibleSurface, visible_depth

import warpfem
from warpfem.sim.surface import REACH, visible_surface


@wp.kernel
def _depths(
    s: VisibleSurface,
    x: wp.array(dtype=wp.vec3),
    tets: wp.array(dtype=wp.vec4i),
    tet_ids: wp.array(dtype=wp.int32),
    weights: wp.array(dtype=wp.vec4),
    bounds: wp.array(dtype=float),
    depth_out: wp.array(dtype=float),
    direction_out: wp.array(dtype=wp.vec3),
):
    i = wp.tid()
    e = tet_ids[i]
    d, g = visible_depth(s, x, e, tets[e], weights[i], -1.0e30, wp.vec3(), bounds[i], 0.0)  # no contact offset
    depth_out[i] = d
    direction_out[i] = g


def _bunny(name: str, scale: float, turn: float, x: float) -> dict:
    return {"name": name, "mesh": "builtin:bunny", "subdivide": 0, "faces": 400, "scale": scale,
            "rotate": [0.0, turn, 0.0], "translate": [x, 1.0, 0.0]}  # fmt: skip


def test_depth_below_the_visible_surface_of_moved_turned_and_scaled_copies(device):
    """Three copies of one bunny (one at rest, one turned and moved, one also scaled: the three share one
    mesh), each turned and moved again as a whole: at points in their tets, the depth below the dense surface
    equals libigl's signed distance to the dense mesh so moved (to 1e-5 of the size), and where deeper than
    1 % of the size, going that depth the way out lands on that mesh (to 1e-5 of the size)."""
    import igl

    scene = warpfem.Scene.from_dict(
        {"object": [_bunny("a", 0.5, 0.0, 0.0), _bunny("b", 0.5, 70.0, 1.0), _bunny("c", 0.8, -40.0, 2.2)]},
        name="copies",
    )
    sim = warpfem.Simulation(scene, device=device)
    model, visible = sim.model, sim.solver.collider.visible
    assert len(sim.solver.collider._dense_meshes) == 1
    c, s = np.cos(0.6), np.sin(0.6)
    turn = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]) @ np.array(
        [[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]
    )
    move = np.array([0.3, -0.2, 0.5])
    x = model.rest_x.numpy().astype(np.float64) @ turn.T + move
    rng = np.random.default_rng(3)
    tets = model.tets.numpy()
    tet_ids = rng.integers(0, len(tets), 3000).astype(np.int32)
    w = rng.dirichlet(np.ones(4), len(tet_ids))
    points = np.einsum("nk,nkd->nd", w, x[tets[tet_ids]])
    depth = wp.zeros(len(tet_ids), dtype=float, device=device)
    direction = wp.zeros(len(tet_ids), dtype=wp.vec3, device=device)
    wp.launch(
        _depths,
        dim=len(tet_ids),
        inputs=[visible, wp.array(x, dtype=wp.vec3, device=device), model.tets, wp.array(tet_ids, device=device),
                wp.array(w, dtype=wp.vec4, device=device), wp.full(len(tet_ids), 1.0e30, dtype=float, device=device)],
        outputs=[depth, direction],
        device=device,
    )  # fmt: skip
    depth, direction = depth.numpy(), direction.numpy()
    tet_body = model.tet_body.numpy()[tet_ids]
    checked = 0
    for b, body in enumerate(model.bodies):
        dense = sim.dense_points(body.name) @ turn.T + move
        mine = np.flatnonzero((tet_body == b) & (depth > -1.0e29))
        dist, *_ = igl.signed_distance(points[mine], dense, body.dense_faces.astype(np.int64))
        np.testing.assert_allclose(depth[mine], -dist, atol=1e-5 * body.size)
        inside = mine[-dist > 1e-2 * body.size]
        landed = points[inside] + depth[inside, None] * direction[inside]
        off, *_ = igl.point_mesh_squared_distance(landed, dense, body.dense_faces.astype(np.int64))
        assert np.sqrt(off.max()) < 1e-5 * body.size, (body.name, np.sqrt(off.max()) / body.size)
        checked += len(inside)
    assert checked > 300


@wp.kernel
def _bounds(
    rest_x: wp.array(dtype=wp.vec3),
    face_depth: wp.array(dtype=float),
    tet_face_start: wp.array(dtype=wp.int32),
    tet_faces: wp.array(dtype=wp.vec3i),
    tet_face_ids: wp.array(dtype=wp.int32),
    tet_ids: wp.array(dtype=wp.int32),
    points: wp.array(dtype=wp.vec3),
    bound_out: wp.array(dtype=float),
):
    i = wp.tid()
    e = tet_ids[i]
    b = float(1.0e30)  # noqa: UP018 (a Warp kernel local it mutates)
    for f in range(tet_face_start[e], tet_face_start[e + 1]):
        b = wp.min(b, depth_above(rest_x, face_depth, tet_faces[f], tet_face_ids[f], points[i]))
    bound_out[i] = b


def test_depth_bound_from_a_face_lattice_never_falls_below_the_depth(device):
    """The bound the collider uses to skip the dense query (``depth_above``), from every surface face
    near a tet, at points in the tets near the surface of a bunny at rest: never below libigl's signed depth
    under the dense mesh, and below zero (the query skipped) at most points that lie outside it by more than
    1 % of the size."""
    import igl

    scene = warpfem.Scene.from_dict({"object": [_bunny("a", 0.5, 30.0, 0.0)]}, name="bound")
    sim = warpfem.Simulation(scene, device=device)
    model, body = sim.model, sim.model.bodies[0]
    starts = model.tet_face_start.numpy()
    near = np.flatnonzero(np.diff(starts) > 0).astype(np.int32)
    rng = np.random.default_rng(5)
    tet_ids = near[rng.integers(0, len(near), 4000)]
    w = rng.dirichlet(np.ones(4), len(tet_ids))
    rest = model.rest_x.numpy().astype(np.float64)
    points = np.einsum("nk,nkd->nd", w, rest[model.tets.numpy()[tet_ids]])
    bound = wp.zeros(len(tet_ids), dtype=float, device=device)
    wp.launch(
        _bounds,
        dim=len(tet_ids),
        inputs=[model.rest_x, model.face_depth, model.tet_face_start, model.tet_faces, model.tet_face_ids,
                wp.array(tet_ids, device=device), wp.array(points, dtype=wp.vec3, device=device)],
        outputs=[bound],
        device=device,
    )  # fmt: skip
    bound = bound.numpy()
    dist, *_ = igl.signed_distance(points, sim.dense_points(body.name), body.dense_faces.astype(np.int64))
    assert np.all(bound >= -dist - 1e-5 * body.size), np.max(-dist - bound) / body.size
    outside = dist > 1e-2 * body.size
    assert outside.sum() > 100
    assert np.mean(bound[outside] < 0.0) > 0.5, np.mean(bound[outside] < 0.0)


def test_a_query_bounded_by_the_lattice_finds_every_depth_inside_and_none_outside(device):
    """The dense query looks no farther than the face lattice's bound on the depth: at points in the tets
    near a bunny's surface, where libigl's signed distance puts a point inside within the query's reach, the
    bounded query gives that depth (to 1e-5 of the size); where it puts a point outside, no positive depth."""
    import igl

    scene = warpfem.Scene.from_dict({"object": [_bunny("a", 0.5, 30.0, 0.0)]}, name="bounded")
    sim = warpfem.Simulation(scene, device=device)
    model, body = sim.model, sim.model.bodies[0]
    near = np.flatnonzero(np.diff(model.tet_face_start.numpy()) > 0).astype(np.int32)
    rng = np.random.default_rng(7)
    tet_ids = wp.array(near[rng.integers(0, len(near), 4000)], device=device)
    w = rng.dirichlet(np.ones(4), len(tet_ids))
    rest = model.rest_x.numpy().astype(np.float64)
    points = np.einsum("nk,nkd->nd", w, rest[model.tets.numpy()[tet_ids.numpy()]])
    bound = wp.zeros(len(tet_ids), dtype=float, device=device)
    wp.launch(
        _bounds,
        dim=len(tet_ids),
        inputs=[model.rest_x, model.face_depth, model.tet_face_start, model.tet_faces, model.tet_face_ids,
                tet_ids, wp.array(points, dtype=wp.vec3, device=device)],
        outputs=[bound],
        device=device,
    )  # fmt: skip
    visible, meshes = visible_surface(model)  # a lone body has no collider; the meshes must stay alive
    depth = wp.zeros(len(tet_ids), dtype=float, device=device)
    direction = wp.zeros(len(tet_ids), dtype=wp.vec3, device=device)
    wp.launch(
        _depths,
        dim=len(tet_ids),
        inputs=[visible, model.rest_x, model.tets, tet_ids, wp.array(w, dtype=wp.vec4, device=device),
                bound],
        outputs=[depth, direction],
        device=device,
    )  # fmt: skip
    depth = depth.numpy()
    dist, *_ = igl.signed_distance(points, sim.dense_points(body.name), body.dense_faces.astype(np.int64))
    inside = (-dist > 0.0) & (-dist < 0.99 * REACH * body.size)
    assert inside.sum() > 200 and (dist > 0.0).sum() > 200
    np.testing.assert_allclose(depth[inside], -dist[inside], atol=1e-5 * body.size)
    assert depth[dist > 0.0].max() <= 1e-5 * body.size

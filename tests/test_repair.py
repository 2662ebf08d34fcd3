"""Hole closing and shells (warpfem.prep.repair) and prepare() on deliberately broken inputs."""

import time

import igl
import numpy as np
import pytest
import trimesh
from mesh_kinds import bowtie, with_flaps, with_flipped_faces

from warpfem.errors import InputError
from warpfem.prep.pipeline import prepare
from warpfem.prep.repair import boundary_loops, cap_loop, ear_clip
from warpfem.prep.surface import load_surface, signed_volume, topology_defects
from warpfem.prep.tetmesh import boundary_faces, tet_signed_volumes


def _write_obj(path, vertices, faces):
    lines = [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_ear_clipping_a_non_convex_polygon():
    # an L shape: area 3, with a reflex corner
    poly = np.array([[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]], dtype=float)
    tris = ear_clip(poly)
    assert tris.shape == (4, 3)
    a, b, c = (poly[tris[:, k]] for k in range(3))
    areas = 0.5 * ((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))
    assert np.all(areas > 0) and areas.sum() == pytest.approx(3.0)


def test_a_cap_restores_the_removed_patch():
    sphere = trimesh.creation.icosphere(subdivisions=2)
    # remove the 6 faces around one vertex of valence 6: a hexagonal hole
    center = np.flatnonzero(np.bincount(sphere.faces.reshape(-1)) == 6)[0]
    kept = sphere.faces[~np.any(sphere.faces == center, axis=1)]
    (loop,) = boundary_loops(kept)
    assert len(loop) == 6
    extra, cap = cap_loop(sphere.vertices, loop)
    assert len(extra) == 0 and len(cap) == 4
    closed = np.vstack([kept, cap])
    assert topology_defects(closed) is None  # closed and consistently wound
    # the flat cap cuts off a thin spherical cap: the volume is a bit smaller, still positive
    assert 0.97 * sphere.volume < signed_volume(sphere.vertices, closed) < sphere.volume


def test_two_shells_merge_select_or_fail(tmp_path):
    big = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    small = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    vertices = np.vstack([big.vertices, small.vertices + [3.0, 0.0, 0.0]])
    # the small sphere is wound inward: it is flipped on its own
    faces = np.vstack([big.faces, small.faces[:, ::-1] + len(big.vertices)])
    path = _write_obj(tmp_path / "two.obj", vertices, faces)

    merged = load_surface(path)
    assert "merged 2 shells into one body" in merged.repairs and "flipped 1 inward shells" in merged.repairs
    assert not merged.overlapping
    assert signed_volume(merged.vertices, merged.faces) == pytest.approx(big.volume + small.volume, rel=1e-9)
    largest = load_surface(path, shells="largest")
    assert signed_volume(largest.vertices, largest.faces) == pytest.approx(big.volume, rel=1e-9)
    second = load_surface(path, shells=1)
    assert signed_volume(second.vertices, second.faces) == pytest.approx(small.volume, rel=1e-9)
    assert np.all(second.vertices[:, 0] > 2.0)
    with pytest.raises(InputError, match="two.obj: 2 separate shells"):
        load_surface(path, shells="error")
    with pytest.raises(InputError, match="two.obj: shell index 2 out of range"):
        load_surface(path, shells=2)


def test_nested_shells_are_flagged(tmp_path):
    outer = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    inner = trimesh.creation.icosphere(subdivisions=1, radius=0.3)
    vertices = np.vstack([outer.vertices, inner.vertices])
    faces = np.vstack([outer.faces, inner.faces + len(outer.vertices)])
    assert load_surface(_write_obj(tmp_path / "nested.obj", vertices, faces)).overlapping


def test_prepare_meshes_two_disjoint_shells_as_one_body(tmp_path):
    a = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    b = trimesh.creation.icosphere(subdivisions=3, radius=0.6)
    vertices = np.vstack([a.vertices, b.vertices + [2.5, 0.0, 0.0]])
    faces = np.vstack([a.faces, b.faces + len(a.vertices)])
    body = prepare(_write_obj(tmp_path / "pair.obj", vertices, faces), faces=400, maxh=0.3)
    volumes = tet_signed_volumes(body.tet_vertices, body.tets)
    assert np.all(volumes > 0)
    centroids = body.tet_vertices[body.tets].mean(axis=1)
    right = centroids[:, 0] > 1.25
    assert right.any() and (~right).any()  # both shells are filled
    # the tets fill the cage around both dense shells; QEM's surface before it kept their volume
    assert body.stats["volume_ratio"] == pytest.approx(1.0, abs=0.05)
    assert volumes.sum() == pytest.approx((a.volume + b.volume) * body.stats["cage_volume_ratio"], rel=1e-6)
    assert 1.0 < body.stats["cage_volume_ratio"] < 1.1
    assert len(boundary_faces(body.tets)) == len(body.coarse_faces)


def test_self_intersecting_input_gets_an_outer_surface(tmp_path):
    # two unit spheres 1.2 apart in one file: their surfaces cross; the body is their union
    sphere = trimesh.creation.icosphere(subdivisions=3)
    vertices = np.vstack([sphere.vertices, sphere.vertices + [1.2, 0.0, 0.0]])
    faces = np.vstack([sphere.faces, sphere.faces + len(sphere.vertices)])
    body = prepare(_write_obj(tmp_path / "union.obj", vertices, faces), faces=600, maxh=0.3)
    assert body.stats["dense_intersecting_pairs"] > 0
    assert "outer surface" in body.stats["rung"]
    assert "intersects itself" in body.stats["failed_rungs"]
    # union of two unit balls at distance d: 2 * (4/3 pi) - lens, lens = pi (4 + d) (2 - d)^2 / 12
    d = 1.2
    union = 2 * 4 / 3 * np.pi - np.pi * (4 + d) * (2 - d) ** 2 / 12
    assert tet_signed_volumes(body.tet_vertices, body.tets).sum() == pytest.approx(union, rel=0.05)
    # the coarse surface hugs the dense one; the dense point deepest inside the union, (1, 0, 0), is
    # sqrt(0.4^2 + 0.8^2) = 0.894 from the circle where the spheres cross
    diag = np.linalg.norm(np.ptp(vertices, axis=0))
    assert body.stats["hausdorff_coarse_to_dense"] < 0.03 * diag
    assert 0.85 < body.stats["hausdorff_dense_to_coarse"] < 0.9
    # every dense vertex is embedded and rebuilt exactly
    rebuilt = np.einsum("nk,nkj->nj", body.embed_bary, body.tet_vertices[body.tets[body.embed_tet]])
    np.testing.assert_allclose(rebuilt, body.dense_vertices, atol=1e-9)


@pytest.mark.parametrize("scale", [1e-9, 1e12])
def test_prepare_works_at_any_coordinate_scale(tmp_path, scale):
    mesh = trimesh.creation.icosphere(subdivisions=3)
    mesh.vertices *= [1.0, 0.7, 0.5]
    body = prepare(_write_obj(tmp_path / "scaled.obj", mesh.vertices * scale, mesh.faces), faces=300, maxh=0.3)
    volumes = tet_signed_volumes(body.tet_vertices, body.tets)
    assert np.all(volumes > 0)
    assert volumes.sum() == pytest.approx(mesh.volume * scale**3, rel=0.05)
    assert body.stats["hausdorff_relative"] < 0.02
    diag = np.linalg.norm(np.ptp(mesh.vertices, axis=0)) * scale
    assert body.stats["hausdorff"] == pytest.approx(body.stats["hausdorff_relative"] * diag, rel=1e-9)
    rebuilt = np.einsum("nk,nkj->nj", body.embed_bary, body.tet_vertices[body.tets[body.embed_tet]])
    np.testing.assert_allclose(rebuilt, body.dense_vertices, rtol=0, atol=1e-9 * scale)
    assert 0 < body.vertex_depth.max() < 0.5 * scale


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("empty.obj", "", "empty.obj: mesh file is empty"),
        ("nan.obj", "v 0 0 0\nv 1 0 nan\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 3 4\nf 1 4 2\nf 2 4 3\n", "NaN or Inf"),
        ("huge.obj", "v 0 0 0\nv 1e200 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n", "too large"),
        ("flat.obj", "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\nf 1 3 4\nf 2 1 4\nf 2 4 3\n", "zero volume"),
        ("point.obj", "v 1 1 1\nv 1 1 1\nv 1 1 1\nf 1 2 3\n", "same position"),
    ],
)
def test_prepare_rejects_broken_files_in_one_line(tmp_path, name, content, message):
    path = tmp_path / name
    path.write_text(content)
    with pytest.raises(InputError, match=message) as err:
        prepare(path, faces=100)
    assert str(err.value).startswith(str(path)) and "\n" not in str(err.value)


def test_flaps_on_edges_are_split_off_and_removed(tmp_path):
    """Two stray triangles welded onto edges of a sphere (each edge then has three faces) leave the sphere."""
    sphere = trimesh.creation.icosphere(subdivisions=3)
    vertices, faces = with_flaps(sphere.vertices, sphere.faces, 2)
    surface = load_surface(_write_obj(tmp_path / "flaps.obj", vertices, faces))
    assert surface.repairs[0] == "split 2 non-manifold edges and 4 vertices where separate sheets met"
    assert "removed 2 shells enclosing no volume (flaps or sheets, 4 faces)" in surface.repairs
    assert len(surface.faces) == len(sphere.faces) and topology_defects(surface.faces) is None
    assert signed_volume(surface.vertices, surface.faces) == pytest.approx(sphere.volume, rel=1e-12)


def test_a_few_flipped_faces_are_turned_back(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=3)
    vertices, faces = with_flipped_faces(sphere.vertices, sphere.faces, 7)
    surface = load_surface(_write_obj(tmp_path / "flipped.obj", vertices, faces))
    assert surface.repairs == ("turned 7 faces wound against their neighbours",)
    np.testing.assert_array_equal(surface.faces, sphere.faces)


def test_a_one_sided_surface_is_refused_in_words(tmp_path):
    # a Moebius strip: 24 quads around a twisted band
    n = 24
    t = np.arange(n) * 2 * np.pi / n
    rows = []
    for s in (-0.2, 0.2):
        rows.append(
            np.column_stack(
                [(1 + s * np.cos(t / 2)) * np.cos(t), (1 + s * np.cos(t / 2)) * np.sin(t), s * np.sin(t / 2)]
            )
        )
    vertices = np.vstack(rows)
    i = np.arange(n)
    j = (i + 1) % n
    # the last quad joins the band's ends crossed over
    top_j, bottom_j = np.where(j == 0, n + j, j), np.where(j == 0, j, n + j)
    faces = np.vstack([np.column_stack([i, top_j, n + i]), np.column_stack([n + i, top_j, bottom_j])])
    with pytest.raises(InputError, match="moebius.obj: one-sided surface .* encloses no volume") as err:
        load_surface(_write_obj(tmp_path / "moebius.obj", vertices, faces))
    assert "\n" not in str(err.value)


def test_two_tets_sharing_an_edge_become_a_body_within_seconds(tmp_path):
    """Split at their shared edge, the two tets touch there: QEM's surfaces cross, so the body is their outer
    surface (it spent minutes in Netgen timeouts when non-manifold input was sent there unbounded)."""
    vertices, faces = bowtie()
    clock = time.perf_counter()
    body = prepare(_write_obj(tmp_path / "bowtie.obj", vertices, faces), faces=1000, maxh=0.3)
    assert time.perf_counter() - clock < 20
    assert "outer surface" in body.stats["rung"]
    assert np.all(tet_signed_volumes(body.tet_vertices, body.tets) > 0)
    # each tet has volume 1/6: the tets fill a cage around both, a little larger; the outer surface rounds
    # the tets' sharp corners, which the cage does not quite reach (libigl's distance to its boundary)
    assert 2 / 6 < tet_signed_volumes(body.tet_vertices, body.tets).sum() < 1.2 * 2 / 6
    cage = boundary_faces(body.tets).astype(np.int64)
    squared, _, _ = igl.point_mesh_squared_distance(body.dense_vertices, body.tet_vertices, cage)
    assert np.sqrt(squared.max()) < 0.02 * np.linalg.norm(np.ptp(vertices, axis=0))
    rebuilt = np.einsum("nk,nkj->nj", body.embed_bary, body.tet_vertices[body.tets[body.embed_tet]])
    np.testing.assert_allclose(rebuilt, body.dense_vertices, atol=1e-9)


def test_meshio_reads_what_trimesh_cannot(tmp_path, monkeypatch):
    """A PLY of quads read through meshio (trimesh made to fail): the unit cube, split into fans."""
    import meshio

    corners = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], dtype=float)
    quads = np.array([[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [1, 3, 7, 5], [3, 2, 6, 7], [2, 0, 4, 6]])
    path = tmp_path / "cube.ply"
    meshio.write(path, meshio.Mesh(corners, [("quad", quads)]), binary=False)

    def fail(*_args, **_kwargs):
        raise ValueError("trimesh cannot read this")

    monkeypatch.setattr(trimesh, "load", fail)
    surface = load_surface(path)
    assert len(surface.faces) == 12 and topology_defects(surface.faces) is None
    assert signed_volume(surface.vertices, surface.faces) == pytest.approx(1.0, rel=1e-12)
    path.write_text("ply\nformat ascii 1.0\nelement vertex 2\nend_header\nnot numbers\n")
    with pytest.raises(InputError, match="cube.ply: unreadable mesh file \\(ValueError: trimesh cannot read this\\)"):
        load_surface(path)

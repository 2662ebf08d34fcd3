"""Loading, repair and validation of surface meshes (warpfem.prep.surface)."""

import numpy as np
import pytest
import trimesh

from warpfem.errors import InputError
from warpfem.prep.surface import load_surface, signed_volume, topology_defects


def _write_obj(path, vertices, faces):
    lines = [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")
    return path


def _write_off(path, vertices, faces):
    lines = ["OFF", f"{len(vertices)} {len(faces)} 0"]
    lines += [f"{x:.17g} {y:.17g} {z:.17g}" for x, y, z in vertices]
    lines += [f"3 {a} {b} {c}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")
    return path


def _components(faces):
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    n = faces.max() + 1
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[0]


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".stl", ".off"])
def test_formats_load_to_the_same_closed_sphere(tmp_path, suffix):
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    path = tmp_path / f"sphere{suffix}"
    sphere.export(path)
    surface = load_surface(path)
    assert len(surface.vertices) == len(sphere.vertices)  # STL stores a triangle soup: welded back
    assert len(surface.faces) == len(sphere.faces)
    assert surface.faces.dtype == np.int32 and surface.vertices.dtype == np.float64
    assert signed_volume(surface.vertices, surface.faces) == pytest.approx(sphere.volume, rel=1e-6)
    assert topology_defects(surface.faces) is None
    if suffix == ".stl":
        assert any("welded" in r for r in surface.repairs)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="nope.obj.*not found"):
        load_surface(tmp_path / "nope.obj")


def test_empty_file(tmp_path):
    path = tmp_path / "empty.ply"
    path.write_bytes(b"")
    with pytest.raises(InputError, match="empty.ply.*empty"):
        load_surface(path)


def test_garbage_file(tmp_path):
    path = tmp_path / "garbage.ply"
    path.write_bytes(b"ply\nthis is not a ply header\n\x00\x01\x02")
    with pytest.raises(InputError, match="garbage.ply") as err:
        load_surface(path)
    assert "\n" not in str(err.value)


def test_obj_without_faces(tmp_path):
    path = tmp_path / "points.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(InputError, match="points.obj.*no faces"):
        load_surface(path)


def test_nan_coordinate(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=1)
    vertices = sphere.vertices.copy()
    vertices[3, 1] = np.nan
    path = _write_obj(tmp_path / "nan.obj", vertices, sphere.faces)
    with pytest.raises(InputError, match="nan.obj.*NaN or Inf"):
        load_surface(path)


def test_large_hole_is_reported_small_hole_is_closed(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=1)
    path = _write_obj(tmp_path / "hole.obj", sphere.vertices, sphere.faces[1:])
    holes = "hole.obj: open surface, it encloses no volume: 1 holes, the largest spans .* of the bounding-box"
    with pytest.raises(InputError, match=holes):
        load_surface(path, max_hole=0.1)
    edges = "hole.obj: open surface, it encloses no volume: not closed: 3 boundary edges"
    with pytest.raises(InputError, match=edges):
        load_surface(path, max_hole=0.0)
    surface = load_surface(path)  # the default limit closes it: the same triangle comes back
    assert any("closed 1 holes" in r for r in surface.repairs)
    assert topology_defects(surface.faces) is None
    assert signed_volume(surface.vertices, surface.faces) == pytest.approx(sphere.volume, rel=1e-12)


def test_flat_closed_surface_is_rejected(tmp_path):
    # a square pillow with both layers in z = 0: closed and manifold but enclosing nothing
    vertices = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=float)
    faces = np.array([[0, 1, 2], [0, 2, 3], [1, 0, 3], [1, 3, 2]])
    path = _write_obj(tmp_path / "flat.obj", vertices, faces)
    with pytest.raises(InputError, match="flat.obj.*zero volume"):
        load_surface(path)


def test_non_manifold_edge_is_split(tmp_path):
    # two tetrahedra sharing the edge (0,1): that edge has four faces; split, they are two closed shells
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, -1, 0], [0, 0, -1]], dtype=float)
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3], [0, 1, 4], [0, 5, 1], [0, 4, 5], [1, 5, 4]])
    surface = load_surface(_write_obj(tmp_path / "bowtie.obj", vertices, faces))
    assert surface.repairs[0] == "split 1 non-manifold edges and 2 vertices where separate sheets met"
    assert "merged 2 shells into one body" in surface.repairs
    assert topology_defects(surface.faces) is None and len(surface.vertices) == 8
    assert signed_volume(surface.vertices, surface.faces) == pytest.approx(2 / 6, rel=1e-12)  # two 1/6 tets


def test_inconsistent_winding_is_turned(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=1)
    faces = sphere.faces.copy()
    faces[5] = faces[5, ::-1]
    surface = load_surface(_write_obj(tmp_path / "twisted.obj", sphere.vertices, faces))
    assert surface.repairs == ("turned 1 faces wound against their neighbours",)
    np.testing.assert_array_equal(surface.faces, sphere.faces)


def test_inside_out_mesh_is_flipped(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=2)
    path = _write_obj(tmp_path / "inverted.obj", sphere.vertices, sphere.faces[:, ::-1])
    surface = load_surface(path)
    assert "flipped inward winding" in surface.repairs
    assert signed_volume(surface.vertices, surface.faces) == pytest.approx(sphere.volume, rel=1e-9)


def test_degenerate_duplicate_faces_and_unused_vertices_are_dropped(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=1)
    vertices = np.vstack([sphere.vertices, [[5.0, 5.0, 5.0]]])  # one unused vertex
    faces = np.vstack([sphere.faces, sphere.faces[:1], [[0, 0, 1]]])  # a duplicate and a degenerate face
    path = _write_off(tmp_path / "messy.off", vertices, faces)
    surface = load_surface(path)
    assert len(surface.faces) == len(sphere.faces)
    assert len(surface.vertices) == len(sphere.vertices)
    joined = " ".join(surface.repairs)
    assert "1 degenerate" in joined and "1 duplicate faces" in joined and "1 unused" in joined
    np.testing.assert_array_equal(surface.vertices, sphere.vertices)  # order and coordinates kept


def test_loop_subdivision(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=1)
    path = _write_obj(tmp_path / "s.obj", sphere.vertices, sphere.faces)
    surface = load_surface(path, subdivide=2)
    assert len(surface.faces) == 16 * len(sphere.faces)
    assert topology_defects(surface.faces) is None
    # Loop subdivision shrinks a convex surface towards its limit surface, inside the control mesh
    assert 0.8 * sphere.volume < signed_volume(surface.vertices, surface.faces) < sphere.volume


def test_builtin_bunny():
    surface = load_surface("builtin:bunny")
    assert surface.vertices.shape == (6102, 3)
    assert surface.faces.shape == (12200, 3)
    assert topology_defects(surface.faces) is None
    assert signed_volume(surface.vertices, surface.faces) > 0


def test_spot_welds_to_one_shell(asset):
    surface = load_surface(asset("spot.obj"))
    assert any(r.startswith("welded") for r in surface.repairs)
    assert _components(surface.faces) == 1
    assert len(surface.vertices) == 2930


def test_horse_is_oriented_outward(asset):
    raw = trimesh.load(asset("horse.ply"), process=False)
    assert signed_volume(raw.vertices, raw.faces) < 0  # the file is wound inside-out
    surface = load_surface(asset("horse.ply"))
    assert "flipped inward winding" in surface.repairs
    assert signed_volume(surface.vertices, surface.faces) == pytest.approx(-signed_volume(raw.vertices, raw.faces))


def test_stanford_bunny_holes_are_closed(asset):
    raw = trimesh.load(asset("stanford-bunny.obj"), process=False, skip_materials=True)
    assert not raw.is_watertight
    surface = load_surface(asset("stanford-bunny.obj"))
    assert any(r.startswith("closed 5 holes") for r in surface.repairs)
    closed = trimesh.Trimesh(surface.vertices, surface.faces, process=False)
    assert closed.is_watertight and closed.is_winding_consistent and closed.volume > 0
    assert len(surface.vertices) == len(raw.vertices)  # ear-clipped caps: no new vertices


def test_a_flat_sheet_is_refused_as_having_no_volume(tmp_path):
    """Every vertex in one (tilted) plane: one line saying it is flat, not a hole count."""
    grid = trimesh.creation.box().vertices[:, :2]
    sheet = trimesh.Trimesh(np.c_[grid, np.zeros(len(grid))], [[0, 1, 2], [1, 3, 2], [4, 5, 6], [5, 7, 6]])
    sheet.apply_transform(trimesh.transformations.rotation_matrix(0.7, [1, 2, 3]))
    sheet.export(tmp_path / "sheet.obj")
    with pytest.raises(InputError, match=r"sheet.obj: flat surface: .* zero volume") as err:
        load_surface(tmp_path / "sheet.obj")
    assert "\n" not in str(err.value)

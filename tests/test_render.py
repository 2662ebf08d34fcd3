"""The preview renderer: camera framing, images against a NumPy pinhole projection, writers, USD read-back."""

import math

import numpy as np
import pytest
import trimesh
from PIL import Image

from warpfem.errors import InputError
from warpfem.io.render import Camera, PreviewWriter, Renderer, auto_camera, framing_box, parse_size, read_usd

W, H = 64, 48


def project(camera, points, width=W, height=H):
    """Pixel (column, row) of world points through a pinhole camera, written independently of the renderer."""
    eye, target = np.array(camera.position), np.array(camera.target)
    f = (target - eye) / np.linalg.norm(target - eye)
    r = np.cross(f, camera.up)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    q = np.atleast_2d(points) - eye
    depth = q @ f
    tan_v = math.tan(math.radians(camera.fov) / 2)
    x = (q @ r) / depth / (tan_v * width / height)
    y = (q @ u) / depth / tan_v
    return np.stack([(x + 1) / 2 * width, (1 - y) / 2 * height], axis=1)


def object_mask(image):
    """Pixels of body 0 (terracotta), lit or in shade: redder than green and blue, unlike grey ground and blue sky."""
    r, g, b = (image[..., k].astype(float) for k in range(3))
    return (r > 1.2 * g) & (r > 1.2 * b) & (r > 30)


def centroid(mask):
    rows, cols = np.nonzero(mask)
    return np.array([cols.mean() + 0.5, rows.mean() + 0.5])


@pytest.fixture
def sphere():
    return trimesh.creation.icosphere(subdivisions=3, radius=0.3)


def test_auto_camera_frames_every_corner_and_centres_the_box():
    lo, hi = np.array([-1.0, 0.0, -0.5]), np.array([1.0, 2.0, 0.5])
    for up_axis in ("Y", "Z"):
        cam = auto_camera(lo, hi, up_axis, aspect=W / H)
        corners = np.array([[a[0], b[1], c[2]] for a in (lo, hi) for b in (lo, hi) for c in (lo, hi)])
        px = project(cam, corners)
        assert np.all((px >= 0) & (px <= [W, H])), px
        # tight: some corner comes within 15 % of an edge
        margin = np.minimum(px, [W, H] - px) / [W, H]
        assert margin.min() < 0.15
        np.testing.assert_allclose(project(cam, 0.5 * (lo + hi))[0], [W / 2, H / 2], atol=1e-6)
        up = np.array([0, 1, 0] if up_axis == "Y" else [0, 0, 1])
        assert np.dot(np.array(cam.position) - 0.5 * (lo + hi), up) > 0  # looks down at the box


def test_framing_box_reaches_down_to_the_ground():
    lo, hi = framing_box([np.array([[0.0, 1.0, 0.0], [1.0, 2.0, 1.0]])], "Y", ground=0.0)
    np.testing.assert_array_equal(lo, [0.0, 0.0, 0.0])
    lo, _ = framing_box([np.array([[0.0, 1.0, 3.0], [1.0, 2.0, 4.0]])], "Z", ground=None)
    np.testing.assert_array_equal(lo, [0.0, 1.0, 3.0])
    lo, hi = framing_box([np.array([[0.0, 1.0, 0.0], [1.0, 3.0, 1.0]])], "Y", ground=0.5, margin=0.1)
    np.testing.assert_allclose([lo, hi], [[-0.25, 0.5, -0.25], [1.25, 3.0, 1.25]])  # 0.1 * largest extent (3 - 0.5)


def test_render_shows_the_body_where_it_is_and_it_moves_down_as_it_falls(sphere, device):
    cam = Camera(position=(0.0, 1.0, 4.0), target=(0.0, 0.6, 0.0), fov=30.0)
    renderer = Renderer([sphere.faces], W, H, device=device, camera=cam, ground=0.0)
    centres, areas = [], []
    for height in (1.0, 0.7, 0.31):
        image = renderer.render([sphere.vertices + [0.0, height, 0.0]])
        assert image.shape == (H, W, 3) and image.dtype == np.uint8
        assert len(np.unique(image.reshape(-1, 3), axis=0)) > 20  # not blank
        mask = object_mask(image)
        expected = project(cam, [0.0, height, 0.0])[0]
        np.testing.assert_allclose(centroid(mask), expected, atol=1.5)
        # area against the projected disk (the sphere subtends a circle of angular radius asin(r / d))
        d = np.linalg.norm(np.array(cam.position) - [0.0, height, 0.0])
        radius_px = math.tan(math.asin(0.3 / d)) / math.tan(math.radians(15.0)) * H / 2
        assert abs(mask.sum() / (math.pi * radius_px**2) - 1) < 0.2
        centres.append(centroid(mask))
        areas.append(mask.sum())
    rows = [c[1] for c in centres]
    assert rows[0] < rows[1] < rows[2]  # image rows grow downward


def test_shadow_and_ground(sphere, device):
    cam = Camera(position=(0.0, 3.0, 3.0), target=(0.0, 0.0, 0.0), fov=40.0)
    renderer = Renderer([sphere.faces], W, H, device=device, camera=cam, ground=0.0)
    image = renderer.render([sphere.vertices + [0.0, 0.3, 0.0]]).astype(int)
    empty = Renderer([sphere.faces], W, H, device=device, camera=cam, ground=0.0)
    far = empty.render([sphere.vertices + [0.0, 0.3, -1e4]]).astype(int)  # the sphere out of view
    assert not object_mask(far).any()
    # the ground is mid grey and is darker where the sphere shades it, and nowhere brighter
    ground = ~object_mask(image)
    darker = (far - image).sum(axis=2) > 30
    assert (darker & ground).sum() > 20
    assert ((image - far).sum(axis=2)[ground] <= 3).all()
    # the camera looks down: with a ground the bottom rows are grey ground, without one they are blue sky
    sky = Renderer([sphere.faces], W, H, device=device, camera=cam, ground=None).render(
        [sphere.vertices + [0.0, 0.3, -1e4]]
    )
    sky = sky.astype(int)
    assert (np.abs(far[-4:, :, 0] - far[-4:, :, 2]) < 12).all()
    assert (sky[..., 2] > sky[..., 0] + 10).all()


def test_two_bodies_get_different_colours(sphere, device):
    cam = Camera(position=(0.0, 0.5, 4.0), target=(0.0, 0.5, 0.0), fov=35.0)
    renderer = Renderer([sphere.faces, sphere.faces], W, H, device=device, camera=cam)
    image = renderer.render([sphere.vertices + [-0.5, 0.5, 0.0], sphere.vertices + [0.5, 0.5, 0.0]])
    left, right = (
        image[H // 2, project(cam, [-0.5, 0.5, 0.0])[0, 0].astype(int)],
        image[H // 2, project(cam, [0.5, 0.5, 0.0])[0, 0].astype(int)],
    )
    assert np.abs(left.astype(int) - right.astype(int)).sum() > 60


def test_renderer_rejects_bad_input(sphere):
    with pytest.raises(InputError, match="no bodies"):
        Renderer([], W, H, device="cpu")
    with pytest.raises(InputError, match="faces"):
        Renderer([np.zeros((3, 2), dtype=np.int32)], W, H, device="cpu")
    renderer = Renderer([sphere.faces], W, H, device="cpu")
    with pytest.raises(InputError, match="points"):
        renderer.render([sphere.vertices[:10]])
    with pytest.raises(InputError, match="same point"):
        Camera((1.0, 1.0, 1.0), (1.0, 1.0, 1.0)).basis()
    for text in ("480", "481x360", "axb", "8x8"):
        with pytest.raises(InputError, match="--size"):
            parse_size(text)
    assert parse_size("640X480") == (640, 480)


def frames_of(tmp_path, n=3):
    rng = np.random.default_rng(0)
    return [rng.integers(0, 255, size=(H, W, 3), dtype=np.uint8) // 64 * 64 + i for i in range(n)]


def test_writers_produce_files_standard_readers_open(tmp_path):
    import imageio_ffmpeg

    frames = frames_of(tmp_path)
    for name in ("a.mp4", "a.gif", "frames"):
        with PreviewWriter(tmp_path / name, fps=30.0, size=(W, H)) as writer:
            for f in frames:
                writer.add(f)
    reader = imageio_ffmpeg.read_frames(str(tmp_path / "a.mp4"))
    meta = next(reader)
    assert tuple(meta["size"]) == (W, H) and meta["fps"] == 30.0
    decoded = [np.frombuffer(b, dtype=np.uint8).reshape(H, W, 3) for b in reader]
    assert len(decoded) == 3
    with Image.open(tmp_path / "a.gif") as gif:
        assert gif.n_frames == 3 and gif.size == (W, H)
        gif.seek(2)
        np.testing.assert_array_equal(np.asarray(gif.convert("RGB")), frames[2])  # <= 256 colours: exact
    pngs = sorted((tmp_path / "frames").iterdir())
    assert [p.name for p in pngs] == ["frame_00000.png", "frame_00001.png", "frame_00002.png"]
    np.testing.assert_array_equal(np.asarray(Image.open(pngs[1])), frames[1])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.gif", "a.mp4", "frames"]  # no temporary left


def test_writer_leaves_nothing_when_no_frame_and_keeps_frames_on_interrupt(tmp_path):
    for name in ("a.mp4", "a.gif", "frames"):
        with pytest.raises(ValueError), PreviewWriter(tmp_path / name, fps=30.0, size=(W, H)):
            raise ValueError("before any frame")
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(KeyboardInterrupt), PreviewWriter(tmp_path / "a.gif", fps=30.0, size=(W, H)) as writer:
        writer.add(frames_of(tmp_path)[0])
        raise KeyboardInterrupt
    with Image.open(tmp_path / "a.gif") as gif:
        assert gif.n_frames == 1
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("")
    for path, needle in [("a.png", "folder"), ("full", "new or empty"), ("no/a.mp4", "does not exist")]:
        with pytest.raises(InputError, match=needle):
            PreviewWriter(tmp_path / path, fps=30.0, size=(W, H))
    with pytest.raises(InputError, match="even"):
        PreviewWriter(tmp_path / "b.mp4", fps=30.0, size=(W + 1, H))


def test_read_usd_returns_what_was_written(tmp_path, sphere):
    from warpfem.io.usd import UsdWriter

    path = tmp_path / "a.usdc"
    frames = [sphere.vertices + [0.0, 1.0 - 0.1 * k, 0.0] for k in range(4)]
    with UsdWriter(path, [("ball", sphere.faces), ("ball2", sphere.faces[::-1])], fps=24.0, up_axis="Z") as usd:
        for k, p in enumerate(frames):
            usd.add_frame(k, [p, p + 1.0])
    anim = read_usd(path)
    assert anim.names == ["/World/ball", "/World/ball2"] and anim.times == [0.0, 1.0, 2.0, 3.0]
    assert anim.fps == 24.0 and anim.up_axis == "Z"
    np.testing.assert_array_equal(anim.faces[0], sphere.faces)
    np.testing.assert_array_equal(anim.faces[1], sphere.faces[::-1])
    np.testing.assert_allclose(anim.points(2.0)[1], frames[2] + 1.0, atol=1e-6)
    lo, hi = anim.bounds()
    np.testing.assert_allclose(lo, np.min([p.min(axis=0) for p in frames], axis=0), atol=1e-6)
    np.testing.assert_allclose(hi, np.max([p.max(axis=0) for p in frames], axis=0) + 1.0, atol=1e-6)
    (tmp_path / "bad.usdc").write_text("not usd")
    for name, needle in [("missing.usdc", "no such file"), ("bad.usdc", "not a USD file")]:
        with pytest.raises(InputError, match=needle):
            read_usd(tmp_path / name)

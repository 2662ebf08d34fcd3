"""Headless preview renders of dense meshes: a Warp ray caster, an automatic camera and video/image writers.

:class:`Renderer` keeps all bodies of a scene in one ``wp.Mesh`` on the simulation's device; each frame
it copies the new points in, refits the BVH, recomputes smooth vertex normals and launches one ray-casting
kernel (``warpfem.kernels.render``). No display server or OpenGL is involved. :class:`PreviewWriter`
streams the frames to an ``.mp4`` (H.264 through the ffmpeg binary shipped in ``imageio-ffmpeg``), a
``.gif`` (Pillow) or a folder of PNG files, atomically like :class:`warpfem.io.usd.UsdWriter`.
:func:`read_usd` reads back the animated meshes of a USD file so it can be rendered elsewhere.
"""

from __future__ import annotations

import math
import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np

from warpfem.errors import InputError

DEFAULT_SIZE = (480, 360)
"""Default preview resolution (width, height) in pixels."""

AUTO_MARGIN = 0.2
"""Side room of the automatic camera's box, as a fraction of the first frame's extent (see :func:`framing_box`)."""

PREVIEW_SUFFIXES = (".mp4", ".gif")
"""Preview files by extension; a path without an extension is a folder of PNG frames."""

PALETTE = (
    (0.80, 0.36, 0.22),
    (0.16, 0.52, 0.62),
    (0.85, 0.64, 0.16),
    (0.42, 0.30, 0.66),
    (0.30, 0.62, 0.30),
    (0.75, 0.28, 0.45),
)
"""Linear RGB albedo of body i: ``PALETTE[i % len(PALETTE)]``."""


@dataclass(frozen=True)
class Camera:
    """A pinhole camera.

    Attributes:
        position: Eye position (m).
        target: The point looked at (m), shown at the image centre.
        up: World up direction; the image's vertical is its component normal to the view direction.
        fov: Vertical field of view (degrees), in (0, 180).
    """

    position: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fov: float = 35.0

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unit forward, right and screen-up vectors.

        Raises:
            InputError: The position equals the target, ``up`` is parallel to the view, or the fov is out of range.
        """
        if not 0.0 < self.fov < 180.0:
            raise InputError(f"camera fov must be in (0, 180) degrees, got {self.fov}")
        forward = np.subtract(self.target, self.position, dtype=np.float64)
        if not np.linalg.norm(forward) > 0:
            raise InputError(f"camera position and target are the same point {tuple(self.position)}")
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, np.asarray(self.up, dtype=np.float64))
        if not np.linalg.norm(right) > 1e-9:
            raise InputError("camera up direction is parallel to its view direction")
        right /= np.linalg.norm(right)
        return forward, right, np.cross(right, forward)


def up_vector(up_axis: str) -> np.ndarray:
    """The unit world up vector of ``"Y"`` or ``"Z"``."""
    return np.array([0.0, 1.0, 0.0] if up_axis == "Y" else [0.0, 0.0, 1.0])


def auto_camera(lo: np.ndarray, hi: np.ndarray, up_axis: str = "Y", aspect: float = 4 / 3, fov: float = 35.0) -> Camera:
    """A camera framing the box ``[lo, hi]``: front-right of it, 20 degrees above, all 8 corners in view.

    The view direction is fixed relative to the world (azimuth 35 degrees from the front axis: +Z for a
    Y-up world, -Y for Z-up), so cameras for different frames of one scene agree. The distance is the
    smallest at which every box corner lies inside the image, plus an 8 % margin.

    Args:
        lo: Box minimum (3,).
        hi: Box maximum (3,).
        up_axis: ``"Y"`` or ``"Z"``.
        aspect: Image width / height.
        fov: Vertical field of view (degrees).

    Returns:
        The camera, looking at the box centre.
    """
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    up = up_vector(up_axis)
    front = np.array([0.0, 0.0, 1.0]) if up_axis == "Y" else np.array([0.0, -1.0, 0.0])
    side = np.cross(up, front)
    az, el = math.radians(35.0), math.radians(20.0)
    back = math.cos(el) * (math.cos(az) * front + math.sin(az) * side) + math.sin(el) * up  # from target to eye
    centre = 0.5 * (lo + hi)
    extent = max(float(np.linalg.norm(hi - lo)), 1e-6)
    probe = Camera(tuple(centre + back), tuple(centre), tuple(up), fov)
    forward, right, screen_up = probe.basis()
    tan_v = math.tan(math.radians(fov) / 2)
    tan_h = tan_v * aspect
    corners = np.array([[a[0], b[1], c[2]] for a in (lo, hi) for b in (lo, hi) for c in (lo, hi)]) - centre
    # a corner at offset q is in view from distance s when |q.right| <= (s + q.forward) tan_h, same for up
    need = np.maximum(
        np.abs(corners @ right) / tan_h - corners @ forward, np.abs(corners @ screen_up) / tan_v - corners @ forward
    )
    distance = 1.08 * max(float(need.max()), 0.05 * extent)
    return Camera(tuple(centre + distance * back), tuple(centre), tuple(up), fov)


def framing_box(
    points: Sequence[np.ndarray], up_axis: str = "Y", ground: float | None = 0.0, margin: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of all ``points``, stretched down to the ground (when there is one) so a fall stays in view.

    Args:
        points: Arrays of shape (n_i, 3).
        up_axis: ``"Y"`` or ``"Z"``.
        ground: Ground height along the up axis, or None.
        margin: Extra room on every horizontal side, as a fraction of the box's largest extent (for
            bodies that will slide or bounce sideways).

    Returns:
        The box's minimum and maximum corners.
    """
    stacked = np.concatenate([np.asarray(p, dtype=np.float64).reshape(-1, 3) for p in points])
    lo, hi = stacked.min(axis=0), stacked.max(axis=0)
    axis = 1 if up_axis == "Y" else 2
    if ground is not None:
        lo[axis] = min(lo[axis], ground)
    pad = np.full(3, margin * float((hi - lo).max()))
    pad[axis] = 0.0
    return lo - pad, hi + pad


def _nice_spacing(size: float) -> float:
    """A grid spacing of 1, 2 or 5 times a power of ten, near ``size / 6``."""
    raw = max(size / 6.0, 1e-9)
    power = 10.0 ** math.floor(math.log10(raw))
    return min((m * power for m in (1.0, 2.0, 5.0, 10.0)), key=lambda s: abs(math.log(s / raw)))


class Renderer:
    """Ray-casts the dense meshes of a scene into RGB images on a Warp device.

    Example::

        renderer = Renderer([faces], width=480, height=360, device="cpu")
        image = renderer.render([points])  # (360, 480, 3) uint8
    """

    def __init__(
        self,
        faces: Sequence[np.ndarray],
        width: int = DEFAULT_SIZE[0],
        height: int = DEFAULT_SIZE[1],
        device: str | None = None,
        camera: Camera | None = None,
        up_axis: str = "Y",
        ground: float | None = 0.0,
    ):
        """Build the combined triangle list; the mesh and BVH are made on the first :meth:`render`.

        Args:
            faces: One (m_i, 3) integer triangle array per body (indices into that body's points).
            width: Image width in pixels (>= 1).
            height: Image height in pixels (>= 1).
            device: Warp device (default: Warp's default device).
            camera: Fixed camera; None: :func:`auto_camera` framing the first frame rendered, stretched
                down to the ground, with :data:`AUTO_MARGIN` room on the sides.
            up_axis: ``"Y"`` or ``"Z"``.
            ground: Height of the ground plane along the up axis, or None for no ground.

        Raises:
            InputError: No bodies, empty or malformed faces, or a size < 1.
        """
        import warp as wp

        if width < 1 or height < 1:
            raise InputError(f"image size must be at least 1x1, got {width}x{height}")
        if not faces:
            raise InputError("nothing to render: no bodies")
        self.width, self.height = int(width), int(height)
        self.device = wp.get_device(device)
        self.camera, self.up_axis, self.ground = camera, up_axis, ground
        self._counts = []
        offset, tris, owner = 0, [], []
        for b, f in enumerate(faces):
            f = np.asarray(f)
            if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0 or not np.issubdtype(f.dtype, np.integer) or f.min() < 0:
                raise InputError(f"body {b}: faces must be a non-empty (m, 3) array of indices >= 0, got {f.shape}")
            count = int(f.max()) + 1
            tris.append(f.astype(np.int32) + offset)
            owner.append(np.full(len(f), b, dtype=np.int32))
            self._counts.append(count)
            offset += count
        self._faces = np.concatenate(tris)
        self._owner = np.concatenate(owner)
        self._mesh = None

    def _build(self, flat: np.ndarray) -> None:
        """Make the mesh, its BVH and the per-face colour tables on the device."""
        import warp as wp

        dev = self.device
        self._points = wp.array(flat, dtype=wp.vec3, device=dev)
        self._mesh = wp.Mesh(points=self._points, indices=wp.array(self._faces.ravel(), dtype=wp.int32, device=dev))
        self._tris = wp.array(self._faces, dtype=wp.vec3i, device=dev)
        self._normals = wp.zeros(len(flat), dtype=wp.vec3, device=dev)
        self._face_body = wp.array(self._owner, dtype=wp.int32, device=dev)
        colors = [PALETTE[b % len(PALETTE)] for b in range(len(self._counts))]
        self._colors = wp.array(np.array(colors, dtype=np.float32), dtype=wp.vec3, device=dev)
        self._image = wp.zeros((self.height, self.width, 3), dtype=wp.uint8, device=dev)

    def _flatten(self, points: Sequence[np.ndarray]) -> np.ndarray:
        if len(points) != len(self._counts):
            raise InputError(f"expected points for {len(self._counts)} bodies, got {len(points)}")
        arrays = []
        for b, (p, count) in enumerate(zip(points, self._counts, strict=True)):
            p = np.asarray(p, dtype=np.float32)
            if p.ndim != 2 or p.shape[1] != 3 or len(p) < count:
                raise InputError(f"body {b}: points must be an (n >= {count}, 3) array, got shape {p.shape}")
            arrays.append(p[:count])
        return np.ascontiguousarray(np.concatenate(arrays))

    def render(self, points: Sequence[np.ndarray]) -> np.ndarray:
        """Render one frame.

        Args:
            points: One (n_i, 3) array of vertex positions per body, in the order of the faces given.

        Returns:
            A (height, width, 3) uint8 RGB image, row 0 at the top.
        """
        import warp as wp

        from warpfem.kernels import render as kernels

        flat = self._flatten(points)
        if self._mesh is None:
            self._build(flat)
        else:
            self._points.assign(flat)
            self._mesh.refit()
        if self.camera is None:
            lo, hi = framing_box([flat], self.up_axis, self.ground, AUTO_MARGIN)
            self.camera = auto_camera(lo, hi, self.up_axis, self.width / self.height)
        dev = self.device
        wp.launch(kernels.zero_normals, dim=len(flat), inputs=[], outputs=[self._normals], device=dev)
        wp.launch(
            kernels.accumulate_normals,
            dim=len(self._faces),
            inputs=[self._points, self._tris],
            outputs=[self._normals],
            device=dev,
        )
        inputs = self._kernel_inputs(flat)
        wp.launch(kernels.render, dim=(self.height, self.width), inputs=inputs, outputs=[self._image], device=dev)
        return self._image.numpy()

    def _kernel_inputs(self, flat: np.ndarray) -> list:
        """The ray caster's camera, light and ground arguments for the current camera."""
        import warp as wp

        cam = self.camera
        forward, right, screen_up = cam.basis()
        tan_v = math.tan(math.radians(cam.fov) / 2)
        up = up_vector(self.up_axis)
        eye = np.asarray(cam.position, dtype=np.float64)
        target = np.asarray(cam.target, dtype=np.float64)
        # key light: above, to the camera's left and slightly in front
        light = 1.2 * up - 0.7 * right - 0.35 * (forward - np.dot(forward, up) * up)
        light /= np.linalg.norm(light)
        size = max(float(np.linalg.norm(flat.max(axis=0) - flat.min(axis=0))), 1e-6)
        ground_u = np.array([1.0, 0.0, 0.0])  # grid lines follow the world axes
        ground_v = np.cross(up, ground_u)
        vec = wp.vec3
        return [
            self._mesh.id,
            self._normals,
            self._face_body,
            self._colors,
            vec(*eye),
            vec(*forward),
            vec(*(right * tan_v * self.width / self.height)),
            vec(*(screen_up * tan_v)),
            vec(*light),
            vec(*up),
            int(self.ground is not None),
            float(self.ground or 0.0),
            vec(*ground_u),
            vec(*ground_v),
            _nice_spacing(size),
            2.0 * tan_v / self.height,
            size,
            6.0 * float(np.linalg.norm(target - eye)),
        ]


def preview_kind(path: str | Path) -> str:
    """``"mp4"``, ``"gif"`` or ``"png"`` (a folder of PNG frames: a path without an extension).

    Raises:
        InputError: Another extension, a missing parent folder, or an existing non-empty folder or file in
            the way of a PNG folder.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix and suffix not in PREVIEW_SUFFIXES:
        raise InputError(
            f"--preview {path}: use a .mp4 or .gif file, or a folder (no extension) for PNG frames, not '{suffix}'"
        )
    if not path.resolve().parent.is_dir():
        raise InputError(f"--preview {path}: folder {path.resolve().parent} does not exist")
    if suffix:
        if path.is_dir():
            raise InputError(f"--preview {path}: is a folder")
        return suffix[1:]
    if path.exists() and (not path.is_dir() or any(path.iterdir())):
        raise InputError(f"--preview {path}: a PNG frame folder must be new or empty")
    return "png"


def parse_size(text: str) -> tuple[int, int]:
    """``"WIDTHxHEIGHT"`` as integers, each in 16..8192 and even (H.264 needs even sizes).

    Raises:
        InputError: Anything else.
    """
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.isdigit() for p in parts):
        raise InputError(f"--size {text}: expected WIDTHxHEIGHT, e.g. 480x360")
    width, height = int(parts[0]), int(parts[1])
    if not (16 <= width <= 8192 and 16 <= height <= 8192 and width % 2 == 0 and height % 2 == 0):
        raise InputError(f"--size {text}: width and height must be even numbers in 16..8192")
    return width, height


class PreviewWriter:
    """Streams RGB frames to an ``.mp4``, a ``.gif`` or a folder of ``frame_00000.png`` files.

    Frames go to a temporary file (or folder) beside the target, moved into place by :meth:`close`, so the
    target never holds a partial result. Used as a context manager it closes on leaving when at least one
    frame was added (so an interrupted or failed run keeps its frames, like
    :class:`warpfem.io.usd.UsdWriter`) and aborts otherwise.

    The mp4 is H.264 (yuv420p, plays everywhere) at the scene's fps. GIF frame delays are whole
    hundredths of a second, and browsers slow down delays under 0.02 s, so a GIF keeps every frame but
    plays at most 50 fps.
    """

    def __init__(self, path: str | Path, fps: float, size: tuple[int, int]):
        """Check the target and open the temporary output.

        Args:
            path: Target ``.mp4``, ``.gif`` or PNG folder (see :func:`preview_kind`).
            fps: Frames per second (> 0).
            size: (width, height) of every frame; even numbers for mp4.

        Raises:
            InputError: A bad path (see :func:`preview_kind`), fps or size.
        """
        self.path = Path(path)
        self.kind = preview_kind(self.path)
        if not (math.isfinite(fps) and fps > 0):
            raise InputError(f"preview fps must be > 0, got {fps}")
        width, height = size
        if self.kind == "mp4" and (width % 2 or height % 2):
            raise InputError(f"an mp4 needs an even width and height, got {width}x{height}")
        self.fps, self.size = float(fps), (int(width), int(height))
        self.frames = 0
        self._closed = False
        self._tmp = self.path.with_name(f".{self.path.stem}.tmp-{os.getpid()}{self.path.suffix}")
        self._gif: list = []
        self._ffmpeg = None
        if self.kind == "png":
            self._tmp.mkdir()
        elif self.kind == "mp4":
            import imageio_ffmpeg

            self._ffmpeg = imageio_ffmpeg.write_frames(
                str(self._tmp),
                self.size,
                fps=self.fps,
                codec="libx264",
                pix_fmt_out="yuv420p",
                macro_block_size=2,
                quality=7,
                output_params=["-movflags", "+faststart"],
            )
            self._ffmpeg.send(None)  # start ffmpeg

    def add(self, image: np.ndarray) -> None:
        """Append one (height, width, 3) uint8 RGB frame."""
        from PIL import Image

        if self._closed:
            raise RuntimeError(f"{self.path}: PreviewWriter is closed")
        if image.shape != (self.size[1], self.size[0], 3) or image.dtype != np.uint8:
            raise ValueError(f"frame must be a ({self.size[1]}, {self.size[0]}, 3) uint8 array, got {image.shape}")
        if self.kind == "mp4":
            self._ffmpeg.send(np.ascontiguousarray(image))
        elif self.kind == "gif":
            self._gif.append(Image.fromarray(image).quantize(256, method=Image.Quantize.MEDIANCUT))
        else:
            Image.fromarray(image).save(self._tmp / f"frame_{self.frames:05d}.png", optimize=False)
        self.frames += 1

    def close(self) -> Path:
        """Finish the file (or folder) and move it into place.

        Returns:
            The target path.

        Raises:
            RuntimeError: No frame was added (the writer is aborted) or the writer is closed.
        """
        if self._closed:
            raise RuntimeError(f"{self.path}: PreviewWriter is already closed")
        if self.frames == 0:
            self.abort()
            raise RuntimeError(f"{self.path}: no frame was added; nothing written")
        try:
            if self.kind == "mp4":
                self._ffmpeg.close()
                self._ffmpeg = None
            elif self.kind == "gif":
                delay = max(20, 10 * round(100.0 / self.fps))
                first, *rest = self._gif
                first.save(self._tmp, save_all=True, append_images=rest, duration=delay, loop=0)
                self._gif = []
            if self.kind == "png" and self.path.is_dir():
                self.path.rmdir()  # checked empty when opened
            os.replace(self._tmp, self.path)
        except BaseException:
            self.abort()
            raise
        self._closed = True
        return self.path

    def abort(self) -> None:
        """Drop everything written so far; the target is untouched."""
        self._closed = True
        self._gif = []
        if self._ffmpeg is not None:
            self._ffmpeg.close()
            self._ffmpeg = None
        if self._tmp.is_dir():
            shutil.rmtree(self._tmp, ignore_errors=True)
        else:
            self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> PreviewWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._closed:
            return
        if self.frames > 0:
            self.close()
        else:
            self.abort()


@dataclass
class UsdAnimation:
    """The animated meshes of a USD file.

    Attributes:
        path: The file.
        names: Prim path of each mesh.
        faces: (m_i, 3) triangles of each mesh (polygons fan-triangulated).
        times: The time codes with samples, increasing (a single 0.0 for a static file).
        fps: ``timeCodesPerSecond`` of the stage.
        up_axis: ``"Y"`` or ``"Z"``.
        stage: The open ``Usd.Stage`` (kept open while its meshes are read).
        point_attrs: The ``points`` attribute of each mesh.
    """

    path: Path
    names: list[str]
    faces: list[np.ndarray]
    times: list[float]
    fps: float
    up_axis: str
    stage: Any
    point_attrs: list[Any]

    def points(self, time: float) -> list[np.ndarray]:
        """World-space points of every mesh at ``time``."""
        from pxr import Usd, UsdGeom

        cache = UsdGeom.XformCache(time)
        out = []
        for attr in self.point_attrs:
            p = np.asarray(attr.Get(Usd.TimeCode(time)), dtype=np.float64)
            m = np.asarray(cache.GetLocalToWorldTransform(attr.GetPrim()), dtype=np.float64)
            out.append(p @ m[:3, :3] + m[3, :3])  # USD matrices act on row vectors
        return out

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Box around every mesh over all times, from the points (m)."""
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for time in self.times:
            for p in self.points(time):
                lo, hi = np.minimum(lo, p.min(axis=0)), np.maximum(hi, p.max(axis=0))
        return lo, hi


def _triangulate(counts: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Fan-triangulate polygons given by face vertex counts and indices."""
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    tris = [
        np.stack([np.full(c - 2, s), s + np.arange(1, c - 1), s + np.arange(2, c)], axis=1)
        for s, c in zip(starts, counts, strict=True)
        if c >= 3
    ]
    return indices[np.concatenate(tris)] if tris else np.zeros((0, 3), dtype=np.int64)


def read_usd(path: str | Path) -> UsdAnimation:
    """Read the meshes of a USD file (as warpfem writes them: ``UsdGeom.Mesh`` prims with sampled points).

    Raises:
        InputError: The file is missing, not USD, or has no mesh with points and faces.
    """
    from pxr import Tf, Usd, UsdGeom

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    try:
        stage = Usd.Stage.Open(str(path))
    except Tf.ErrorException:
        stage = None
    if stage is None:
        raise InputError(f"{path}: not a USD file that can be opened")
    names, faces, attrs, times = [], [], [], set()
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.Mesh):
            continue
        mesh = UsdGeom.Mesh(prim)
        counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get() or [], dtype=np.int64)
        indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], dtype=np.int64)
        attr = mesh.GetPointsAttr()
        samples = attr.GetTimeSamples()
        first = attr.Get(Usd.TimeCode(samples[0]) if samples else Usd.TimeCode.Default())
        if first is None or len(first) == 0 or counts.sum() != len(indices) or len(indices) == 0:
            continue
        tris = _triangulate(counts, indices)
        if len(tris) == 0 or tris.max() >= len(first):
            raise InputError(f"{path}: mesh {prim.GetPath()} has face indices beyond its {len(first)} points")
        names.append(str(prim.GetPath()))
        faces.append(tris)
        attrs.append(attr)
        times.update(samples)
    if not names:
        raise InputError(f"{path}: no UsdGeom.Mesh with points and faces in it")
    up_axis = UsdGeom.GetStageUpAxis(stage)
    return UsdAnimation(
        path=path,
        names=names,
        faces=faces,
        times=sorted(times) or [0.0],
        fps=float(stage.GetTimeCodesPerSecond()),
        up_axis="Z" if up_axis == UsdGeom.Tokens.z else "Y",
        stage=stage,
        point_attrs=attrs,
    )

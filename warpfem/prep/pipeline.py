"""Preprocessing of one body: load, simplify, validate, tetrahedralize, embed, distance field; cached.

Results are in the mesh file's own coordinates; the simulator applies the scene's uniform scale,
rotation and translation afterwards. Internally every stage works on coordinates translated and scaled
to a unit bounding-box diagonal, so a file's scale (1e-9 or 1e12 units) changes nothing.

When a stage fails, the retry ladder (:data:`LADDER`) tries the next rung: the same coarse surface with
other Netgen settings, other face counts, then a clean outer surface rebuilt from the generalized winding
number (for input that intersects itself). Each coarse surface is validated before Netgen sees it
(closed, manifold, no self-intersection); each tet mesh is accepted only if its tets are positive, its
worst dihedral angle is at least :data:`MIN_DIHEDRAL_DEG`, its boundary is the coarse surface and its
volume within :data:`VOLUME_TOLERANCE` of the dense mesh's. QEM, the outer surface and Netgen run in
child processes under a time limit each, so a crash or hang there is a failed rung, not a dead caller.

The cache is content-addressed: a file is named by the sha256 of the welded input mesh and the
parameters, so an edited mesh or changed parameter never hits a stale entry; it is written atomically
and carries a checksum of its arrays, so a damaged or truncated entry is rebuilt, not loaded. A small
index entry per (file bytes, parameters) names that file, so a cached mesh is found without reading and
repairing the mesh again (USD files excepted: a layer can pull in others). The collision samples of a
prepared body are cached beside it (:func:`cached_surface_samples`).
"""

from __future__ import annotations

import functools
import hashlib
import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np

from warpfem.errors import InputError
from warpfem.prep import samples
from warpfem.prep.embedding import embed, outside_distance
from warpfem.prep.geometry import LATTICE_POINTS, face_lattice
from warpfem.prep.samples import SurfaceSamples, surface_samples
from warpfem.prep.sizing import DEFAULT_MAX_TETS, SIZING_FORMAT
from warpfem.prep.surface import Surface, load_surface, source_file, subdivide_surface

CACHE_FORMAT = 4
"""Version of the cache file layout; entries are also keyed by :func:`code_digest`, so preprocessing code
that changed never reads what older code prepared."""

PREP_KERNELS = ("distance", "embedding", "intersect", "thickness")
"""The ``warpfem.kernels`` modules preprocessing runs."""


@functools.cache
def code_digest() -> str:
    """A digest of the preprocessing source and the kernels it runs: what decides a body besides its inputs.

    Not :mod:`warpfem.prep.samples`, whose choice of collision samples is cached under a key of its own. Not the
    versions of the packages that make the meshes: a cache prepared where Netgen is installed is
    read where it is not (a GPU machine), and an older Netgen's mesh is still a valid one.
    """
    from warpfem.kernels import embedding as kernel

    kernel_dir = Path(kernel.__file__).parent
    digest = hashlib.sha256()
    own = sorted(p for p in Path(__file__).parent.glob("*.py") if p.name != Path(samples.__file__).name)
    files = own + [kernel_dir / f"{k}.py" for k in PREP_KERNELS]
    for path in files:
        digest.update(path.name.encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()


INSIDE_EPS = 1e-9
"""A dense vertex whose smallest barycentric coordinate is >= -this counts as inside its tet."""

MIN_DIHEDRAL_DEG = 0.5
"""Quality bound: every accepted tet has all six dihedral angles at least this (degrees). Netgen keeps
the coarse surface, so slivers between nearly coplanar surface triangles cannot be optimized away; at 1
degree homer.obj and cow.obj at 3,000 faces fail on every rung (see docs/preprocessing.md)."""

VOLUME_TOLERANCE = 0.10
"""Accepted relative difference between the tet mesh's volume and the dense surface's (for input that
intersects itself or has overlapping shells: the outer surface's). QEM of armadillo.off to 300 faces
loses 9.4%, to 1,000 faces 3%."""


BUDGET_S = 60.0
"""Default time budget of one :func:`prepare` (seconds): no rung starts after it, and every child stage's
time limit is cut to what is left of it, so a mesh no rung can handle ends in a one-line reason."""

NETGEN_SHARE = 0.5
"""Netgen may use at most this fraction of the budget left when it starts, so that a rung stuck in
Netgen (slivers it keeps optimizing) leaves time for the rungs after it."""

MIN_TRIANGLE_ANGLE_DEG = 0.5
"""A coarse surface with a triangle whose smallest angle is below this (degrees) is not given to Netgen
as it is: Netgen keeps the surface, and the tets on such needles are slivers (a CAD part's QEM surface:
0.004 deg, tets of 0.006 deg). The remeshing rungs even its triangles out first. QEM surfaces of the
scans in docs/preprocessing.md have no angle below 1.1 deg at 400 to 2,500 faces."""


@dataclass(frozen=True)
class Rung:
    """One attempt of the retry ladder.

    Attributes:
        label: What the rung does, as reported in ``stats["rung"]``.
        source: ``"qslim"`` (QEM of the repaired dense surface) or ``"outer"`` (QEM of the generalized
            winding number's marching-cubes surface).
        faces_factor: Target face count relative to the requested one.
        maxh_factor: Netgen's maxh relative to the requested one.
        optsteps: Netgen's 3D optimization passes.
        cells_factor: Outer-surface grid resolution relative to :func:`warpfem.prep.simplify.outer_cells`.
        remesh: Whether the surface is remeshed to even triangles (:func:`warpfem.prep.simplify.remesh`)
            from QEM at :data:`REMESH_INPUT_FACTOR` times the target, instead of QEM to the target.
    """

    label: str
    source: str
    faces_factor: float = 1.0
    maxh_factor: float = 1.0
    optsteps: int = 3
    cells_factor: float = 1.0
    remesh: bool = False


REMESH_INPUT_FACTOR = 4.0
"""A remeshing rung remeshes QEM's surface at this many times the target faces (sharp features kept)."""

LADDER = (
    Rung("qslim", "qslim"),
    Rung("qslim, Netgen maxh/2 and 8 optimization passes", "qslim", maxh_factor=0.5, optsteps=8),
    Rung("qslim at 0.8x faces", "qslim", faces_factor=0.8),
    Rung("qslim at 1.25x faces", "qslim", faces_factor=1.25),
    Rung("qslim, remeshed to even triangles", "qslim", remesh=True),
    Rung("outer surface (winding number + marching cubes) + qslim", "outer"),
    Rung("outer surface, remeshed to even triangles", "outer", remesh=True),
    Rung("outer surface on a 0.6x grid (smoother) + qslim", "outer", cells_factor=0.6),
    Rung("outer surface + qslim at 0.8x faces, Netgen 8 passes", "outer", faces_factor=0.8, optsteps=8),
)
"""The retry ladder, tried in order until a rung gives a valid tet mesh (``stats["rung"]`` says which)."""

_STAT_PREFIX = "stat__"


@dataclass(frozen=True)
class PreparedBody:
    """A body ready to simulate, in its mesh's own coordinates (units of the mesh file).

    Attributes:
        dense_vertices: (n, 3) float64 rendered surface positions.
        dense_faces: (m, 3) int32 rendered surface triangles, outward.
        coarse_vertices: (k, 3) float64 simplified surface positions (== ``tet_vertices[:k]``).
        coarse_faces: (l, 3) int32 simplified surface triangles, indexing ``coarse_vertices``.
        boundary_faces: (l, 3) int32 the same triangles indexing ``tet_vertices``.
        tet_vertices: (p, 3) float64 tet mesh vertex positions.
        tets: (q, 4) int32 tets, all with positive det(b-a, c-a, d-a).
        embed_tet: (n,) int32 tet of each dense vertex.
        embed_bary: (n, 4) float64 barycentric coordinates of each dense vertex in its tet.
        vertex_depth: (p,) float64 distance of each tet vertex to the coarse surface (0 on it).
        vertex_grad: (p, 3) float64 unit gradient of that distance, pointing out of the body.
        face_depth: (l, LATTICE_POINTS) float64 depth of the dense surface below the lattice points of each boundary
            face (:func:`warpfem.prep.geometry.face_lattice`), negative where the cage lies outside it.
        stats: What was made and how long it took (see :func:`prepare`).
    """

    dense_vertices: np.ndarray
    dense_faces: np.ndarray
    coarse_vertices: np.ndarray
    coarse_faces: np.ndarray
    boundary_faces: np.ndarray
    tet_vertices: np.ndarray
    tets: np.ndarray
    embed_tet: np.ndarray
    embed_bary: np.ndarray
    vertex_depth: np.ndarray
    vertex_grad: np.ndarray
    face_depth: np.ndarray
    stats: dict[str, float | int | str]


_ARRAY_FIELDS = tuple(f.name for f in fields(PreparedBody) if f.name != "stats")


def cache_key(surface: Surface, faces: int, subdivide: int, maxh: float, options: str = "") -> str:
    """Return the sha256 hex digest naming the cache entry of a welded surface and the parameters.

    Args:
        surface: The loaded, welded surface before subdivision.
        faces: Target coarse face count.
        subdivide: Loop subdivision rounds.
        maxh: Relative maximum tet edge length.
        options: Any further parameters that change the result, as text.

    Returns:
        64 hex characters.
    """
    digest = hashlib.sha256()
    digest.update(
        f"warpfem-prepare v{CACHE_FORMAT} {code_digest()} faces={faces} subdivide={subdivide} maxh={maxh!r}"
        f" {options}\n".encode()
    )
    digest.update(np.ascontiguousarray(surface.vertices, dtype="<f8").tobytes())
    digest.update(np.ascontiguousarray(surface.faces, dtype="<i4").tobytes())
    return digest.hexdigest()


def _read_cache(path: Path) -> PreparedBody | None:
    """Return the body stored at ``path``, or None if it is absent, unreadable or incomplete."""
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: np.array(data[name]) for name in _ARRAY_FIELDS}
            stats = {key[len(_STAT_PREFIX) :]: data[key].item() for key in data.files if key.startswith(_STAT_PREFIX)}
            checksum = str(data["checksum"])
    except Exception:  # a damaged file can fail in zipfile, numpy or the OS layer: rebuild it
        return None
    if checksum != _checksum(arrays):
        return None
    n, p = len(arrays["dense_vertices"]), len(arrays["tet_vertices"])
    consistent = (
        arrays["embed_tet"].shape == (n,)
        and arrays["embed_bary"].shape == (n, 4)
        and arrays["vertex_depth"].shape == (p,)
        and arrays["vertex_grad"].shape == (p, 3)
        and arrays["face_depth"].shape == (len(arrays["boundary_faces"]), LATTICE_POINTS)
        and arrays["tets"].ndim == 2
        and arrays["tets"].shape[1:] == (4,)
    )
    return PreparedBody(**arrays, stats=stats) if consistent else None


def _checksum(arrays: dict[str, np.ndarray]) -> str:
    """sha256 over the arrays' names, dtypes, shapes and bytes."""
    digest = hashlib.sha256()
    for name in _ARRAY_FIELDS:
        array = np.ascontiguousarray(arrays[name])
        digest.update(f"{name} {array.dtype.str} {array.shape}\n".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def _write_cache(path: Path, body: PreparedBody) -> None:
    """Write ``body`` to ``path`` atomically (temporary file in the same folder, then rename)."""
    payload = {name: getattr(body, name) for name in _ARRAY_FIELDS}
    payload["checksum"] = np.array(_checksum(payload))
    payload.update({_STAT_PREFIX + key: np.array(value) for key, value in body.stats.items()})
    _save_atomically(path, lambda stream: np.savez(stream, **payload))


def _save_atomically(path: Path, write: Callable) -> None:
    """Call ``write(stream)`` on a temporary file beside ``path``, then rename it to ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.stem + ".", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as stream:
            write(stream)
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise


def _source_index(cache_dir: Path, mesh: str | Path, params: str) -> Path | None:
    """The index entry naming the cache file of ``mesh`` prepared with ``params``, keyed by its file's bytes.

    None where no one file decides the mesh (:func:`~warpfem.prep.surface.source_file`).
    """
    source = source_file(mesh)
    if source is None:
        return None
    digest = hashlib.sha256(f"warpfem-source v{CACHE_FORMAT} {code_digest()} {params}\n".encode())
    digest.update(source.read_bytes())
    return Path(cache_dir) / f"source-{digest.hexdigest()}.txt"


def _read_indexed(index: Path | None) -> tuple[Path, PreparedBody] | None:
    """The cache file an index entry names and the body in it, if both are there and sound."""
    try:
        key = index.read_text().strip()
    except (AttributeError, OSError, UnicodeDecodeError):
        return None
    if len(key) != 64 or not all(c in "0123456789abcdef" for c in key):
        return None
    path = index.parent / f"{key}.npz"
    body = _read_cache(path)
    return None if body is None else (path, body)


SAMPLES_FORMAT = 2
"""Version of the cached collision samples' layout; they are also keyed by the source of
:mod:`warpfem.prep.samples`, so a change to how samples are chosen never reads old ones."""


def cached_surface_samples(
    body: PreparedBody, spacing: float, tolerance: float, cache_dir: Path | None, skin_spacing: float | None = None
) -> SurfaceSamples:
    """:func:`~warpfem.prep.samples.surface_samples` of ``body``'s dense mesh, read from ``cache_dir`` when there.

    Keyed by the dense mesh's bytes, ``spacing``, ``tolerance``, ``skin_spacing`` (mesh units) and the samples
    module's source; None: computed, nothing stored.
    """
    if cache_dir is None:
        return surface_samples(body.dense_vertices, body.dense_faces, spacing, tolerance, skin_spacing)
    key = f"{spacing!r} {tolerance!r} {skin_spacing!r}"
    digest = hashlib.sha256(f"warpfem-samples v{SAMPLES_FORMAT} {key}\n".encode())
    digest.update(Path(samples.__file__).read_bytes())
    digest.update(np.ascontiguousarray(body.dense_vertices, dtype="<f8").tobytes())
    digest.update(np.ascontiguousarray(body.dense_faces, dtype="<i4").tobytes())
    path = Path(cache_dir) / f"samples-{digest.hexdigest()}.npz"
    try:
        with np.load(path, allow_pickle=False) as data:
            found = SurfaceSamples(*(np.array(data[k]) for k in ("collision", "skin", "face", "face_bary")))
        if _samples_fit(found, len(body.dense_vertices), len(body.dense_faces)):
            return found
    except Exception:  # absent, or damaged anywhere from zipfile to the OS layer: compute it again
        pass
    made = surface_samples(body.dense_vertices, body.dense_faces, spacing, tolerance, skin_spacing)
    arrays = {"collision": made.collision, "skin": made.skin, "face": made.face, "face_bary": made.face_bary}
    _save_atomically(path, lambda stream: np.savez(stream, **arrays))
    return made


def _samples_fit(found: SurfaceSamples, vertices: int, faces: int) -> bool:
    """Whether cached samples index a dense mesh of ``vertices`` vertices and ``faces`` triangles."""
    picks = all(
        len(a) and a.dtype.kind == "i" and 0 <= a.min() and a.max() < vertices for a in (found.collision, found.skin)
    )
    face, bary = found.face, found.face_bary
    on_faces = (
        face.dtype.kind == "i"
        and bary.shape == (len(face), 3)
        and (len(face) == 0 or 0 <= face.min() <= face.max() < faces)
    )
    return picks and on_faces


@dataclass
class _Attempt:
    """Coarse surfaces made so far (memoized per rung source), failures, time per stage and the deadline."""

    dense: Surface
    faces: int
    timeout_s: float
    say: Callable[[str], None]
    dense_volume: float
    dense_clean: bool
    surfaces: dict[tuple, tuple[np.ndarray, np.ndarray, float, dict[str, float]] | InputError]
    seconds: dict[str, float]
    deadline: float = float("inf")

    def limit(self, share: float = 1.0) -> float:
        """Time limit of the next child stage: ``timeout_s``, cut to ``share`` of what is left of the budget.

        Raises:
            InputError: When the budget is spent.
        """
        left = self.deadline - time.perf_counter()
        if left <= 0:
            raise InputError(f"{self.dense.source}: the time budget is spent")
        return min(self.timeout_s, share * left)

    def coarse(self, rung: Rung) -> tuple[np.ndarray, np.ndarray, float, dict[str, float]]:
        """Return the validated coarse surface of ``rung`` (the cage), its reference volume and cage stats.

        The reference is the dense surface's volume, or, for an outer surface made because the dense
        one intersects itself or has overlapping shells, the volume of that outer surface. The stats are
        :func:`warpfem.prep.cage.enclose`'s plus the QEM surface's and the cage's volume over the reference.

        Raises:
            InputError: The memoized reason why this rung's surface could not be made or is invalid.
        """
        from warpfem.prep.simplify import outer_cells

        target = max(4, round(self.faces * rung.faces_factor))
        cells = outer_cells(target) if rung.source == "outer" else 0
        key = (rung.source, target, max(8, round(cells * rung.cells_factor)) if cells else 0, rung.remesh)
        if key not in self.surfaces:
            try:
                self.surfaces[key] = self._make(rung.source, target, key[2], rung.remesh)
            except InputError as err:
                self.surfaces[key] = err
        made = self.surfaces[key]
        if isinstance(made, InputError):
            raise made
        return made

    def _clock(self, stage: str, since: float) -> float:
        """Add the time since ``since`` to ``stage``; return the time now."""
        now = time.perf_counter()
        self.seconds[stage] = self.seconds.get(stage, 0.0) + now - since
        return now

    def _make(
        self, source: str, target: int, cells: int, remesh: bool
    ) -> tuple[np.ndarray, np.ndarray, float, dict[str, float]]:
        from warpfem.prep.cage import enclose
        from warpfem.prep.intersect import intersecting_faces
        from warpfem.prep.simplify import outer_surface, simplify, smallest_angle
        from warpfem.prep.simplify import remesh as remesh_surface
        from warpfem.prep.surface import signed_volume

        name = self.dense.source
        vertices, faces = self.dense.vertices, self.dense.faces
        reference = self.dense_volume
        if source != "outer" and self.dense.overlapping:
            raise InputError(f"{name}: shells overlap, so the body is their union (an outer surface)")
        clock = time.perf_counter()
        if source == "outer":
            self.say(f"{name}: rebuilding the outer surface on a {cells}-cell grid")
            vertices, faces = outer_surface(vertices, faces, cells, name=name, timeout_s=self.limit())
            if not self.dense_clean:
                reference = signed_volume(vertices, faces)
            clock = self._clock("outer", clock)
        goal = round(REMESH_INPUT_FACTOR * target) if remesh else target
        self.say(f"{name}: simplifying {len(faces)} faces to {goal}")
        coarse_v, coarse_f = simplify(vertices, faces, goal, name=name, timeout_s=self.limit())
        clock = self._clock("simplify", clock)
        if remesh:
            if intersecting_faces(coarse_v, coarse_f)[0]:  # Netgen's surface mesher crashes on these
                raise InputError(f"{name}: simplified surface ({len(coarse_f)} faces) intersects itself")
            self.say(f"{name}: remeshing {len(coarse_f)} faces to about {target} even triangles")
            coarse_v, coarse_f = remesh_surface(coarse_v, coarse_f, target, name=name, timeout_s=self.limit())
            clock = self._clock("remesh", clock)
        angle = smallest_angle(coarse_v, coarse_f)
        if angle < MIN_TRIANGLE_ANGLE_DEG:
            raise InputError(
                f"{name}: the simplified surface has needle triangles (smallest angle {angle:.2g} deg), on which"
                " Netgen makes slivers"
            )
        pairs, _ = intersecting_faces(coarse_v, coarse_f)
        clock = self._clock("validate", clock)
        if pairs:
            raise InputError(f"{name}: simplified surface ({len(coarse_f)} faces) intersects itself ({pairs} pairs)")
        self.say(f"{name}: enclosing the dense surface in the coarse one")
        cage_v, cage = enclose(coarse_v, coarse_f, self.dense.vertices, lambda v, f: intersecting_faces(v, f)[0] > 0)
        self._clock("cage", clock)
        cage["qem_volume_ratio"] = signed_volume(coarse_v, coarse_f) / reference
        cage["cage_volume_ratio"] = signed_volume(cage_v, coarse_f) / reference
        return cage_v, coarse_f, reference, cage


def _tet_mesh(
    attempt: _Attempt, rung: Rung, maxh: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, float]]:
    """Run one rung: coarse surface, Netgen, quality and volume checks (raises InputError on failure)."""
    from warpfem.prep.tetmesh import tet_quality, tetrahedralize

    name = attempt.dense.source
    coarse_v, coarse_f, reference, cage = attempt.coarse(rung)
    diag = float(np.linalg.norm(coarse_v.max(axis=0) - coarse_v.min(axis=0)))
    h = maxh * rung.maxh_factor * diag
    attempt.say(f"{name}: tetrahedralizing {len(coarse_f)} faces (maxh {h:.4g} of a unit diagonal)")
    clock = time.perf_counter()
    try:
        tet_v, tets = tetrahedralize(
            coarse_v, coarse_f, h, timeout_s=attempt.limit(NETGEN_SHARE), name=name, optsteps=rung.optsteps
        )
    finally:
        attempt.seconds["tetrahedralize"] = attempt.seconds.get("tetrahedralize", 0.0) + time.perf_counter() - clock
    dihedral, ratio = tet_quality(tet_v, tets)
    if dihedral.min() < MIN_DIHEDRAL_DEG:
        raise InputError(f"{name}: worst tet dihedral angle {dihedral.min():.3g} deg is below {MIN_DIHEDRAL_DEG:g}")
    volume_ratio = cage["qem_volume_ratio"]
    if not abs(volume_ratio - 1.0) <= VOLUME_TOLERANCE:
        raise InputError(
            f"{name}: the simplified surface's volume is {volume_ratio:.3f}x the reference (dense or outer)"
        )
    quality = {
        "tet_min_dihedral_deg": float(dihedral.min()),
        "tet_min_radius_ratio": float(ratio.min()),
        "volume_ratio": float(volume_ratio),
        "cage_volume_ratio": float(cage["cage_volume_ratio"]),
        "cage_offset": float(cage["cage_offset"]),
        "cage_outside": float(cage["cage_outside"]),
        "cage_outside_max": float(cage["cage_outside_max"]),
        "maxh_absolute": h,
    }
    return coarse_v, coarse_f, tet_v, tets, quality


def _sized(
    unit: Surface, faces: int, maxh: float, across: float, max_tets: int, say: Callable[[str], None]
) -> tuple[int, float, dict[str, float | int | str]]:
    """The face count and maxh (unit diagonal) sized from the body's thickness, and what was chosen, as stats."""
    from warpfem.prep.sizing import size_from_thickness

    if not across:
        return faces, maxh, {}
    say(f"{unit.source}: sizing tets to {across:g} across the body's thickness")
    sizing = size_from_thickness(unit.vertices, unit.faces, across, max_tets, faces, maxh)
    stats = {"tets_across": across, "max_tets": max_tets, "sizing_capped": int(sizing.capped)}
    return sizing.faces, sizing.maxh, stats | {"thickness_relative": sizing.thickness}


BUDGET_SLACK = 1.25
"""A body sized by thickness whose tets exceed its budget by more than this factor is sized once more."""


def _climb(attempt: _Attempt, maxh: float, deadline: float):
    """Climb the retry ladder to a valid tet mesh: ``_tet_mesh``'s result, the rung's index and the failures."""
    name, failures = attempt.dense.source, []
    for index, rung in enumerate(LADDER):
        if index > 0 and time.perf_counter() >= deadline:  # the first rung always runs, within what is left
            raise InputError(
                f"{name}: no valid tet mesh at {attempt.faces} faces within the time budget; rungs 1-{index} failed:"
                f" {' '.join(failures)}; rungs {index + 1}-{len(LADDER)} not tried (a larger budget tries them)"
            )
        attempt.say(f"{name}: rung {index + 1}/{len(LADDER)}: {rung.label}")
        try:
            return (*_tet_mesh(attempt, rung, maxh), index, failures)
        except InputError as err:
            reason = str(err).removeprefix(f"{name}: ")
            failures.append(f"{index + 1}) {reason}")
            attempt.say(f"{name}: rung {index + 1} failed: {reason}")
    raise InputError(f"{name}: no valid tet mesh at {attempt.faces} faces, every rung failed: {' '.join(failures)}")


def _sized_tets(attempt: _Attempt, maxh: float, sizing: tuple[float, int], name: str) -> tuple[tuple, dict]:
    """:func:`_climb` at the size ``sizing`` (tets across, tet budget) gives ``attempt``'s surface.

    Sized once more where Netgen overran the budget. Returns the climb's result and the sizing's stats.
    """
    unit, faces, say, deadline = attempt.dense, attempt.faces, attempt.say, attempt.deadline
    seconds = attempt.seconds
    clock = time.perf_counter()
    sized_faces, sized_maxh, sized = _sized(unit, faces, maxh, *sizing, say)
    seconds["sizing"] = time.perf_counter() - clock
    climbed = _climb(replace(attempt, faces=sized_faces), sized_maxh, deadline)
    tets, (across, max_tets) = climbed[3], sizing
    if across and len(tets) > BUDGET_SLACK * max_tets and time.perf_counter() < deadline:
        # Netgen filled the body more densely than the sizing estimated: size once more for a budget scaled
        # down by the square root of the overrun (a full correction overshoots: fewer faces make fewer tets too)
        say(f"{name}: {len(tets)} tets for a budget of {max_tets}: sizing again")
        budget = max(1, round(max_tets * (max_tets / len(tets)) ** 0.5))
        sized_faces, sized_maxh, resized = _sized(unit, faces, maxh, across, budget, say)
        sized = resized | {"max_tets": max_tets, "sized_twice": 1}
        climbed = _climb(replace(attempt, faces=sized_faces, surfaces={}), sized_maxh, deadline)
    return climbed, sized


def _build(
    dense: Surface,
    faces: int,
    maxh: float,
    timeout_s: float,
    deadline: float,
    say: Callable[[str], None],
    sizing: tuple[float, int] = (0.0, 0),
) -> tuple[dict[str, np.ndarray], dict[str, float | int | str]]:
    """Climb the retry ladder to a valid tet mesh, then embed and compute the distance field and stats.

    ``dense`` is in the caller's coordinates; the work is done on a copy scaled to a unit diagonal. No rung
    but the first starts after ``deadline`` (a :func:`time.perf_counter` value). ``sizing`` is (tets across, tet budget)
    for :func:`warpfem.prep.sizing.size_from_thickness`; 0 tets across: ``faces`` and ``maxh`` as given.
    """
    from warpfem.prep.distance import distance_field, hausdorff
    from warpfem.prep.intersect import intersecting_faces
    from warpfem.prep.surface import signed_volume

    name = dense.source
    center = 0.5 * (dense.vertices.max(axis=0) + dense.vertices.min(axis=0))
    scale = float(np.linalg.norm(dense.vertices.max(axis=0) - dense.vertices.min(axis=0)))
    unit = replace(dense, vertices=(dense.vertices - center) / scale)

    clock = time.perf_counter()
    dense_pairs, _ = intersecting_faces(unit.vertices, unit.faces)
    seconds = {"validate": time.perf_counter() - clock}
    # a surface crossing itself or overlapping shells count some volume twice: the outer surface's is used
    clean = dense_pairs == 0 and not dense.overlapping
    volume = signed_volume(unit.vertices, unit.faces)
    attempt = _Attempt(unit, faces, timeout_s, say, volume, clean, {}, seconds, deadline)
    (coarse_v, coarse_f, tet_v, tets, quality, index, failures), sized = _sized_tets(attempt, maxh, sizing, name)

    boundary = coarse_f.copy()  # tetrahedralize keeps the surface points first, so these index tet_v
    clock = time.perf_counter()
    say(f"{name}: embedding {len(unit.vertices)} dense vertices in {len(tets)} tets")
    try:
        embed_tet, embed_bary = embed(unit.vertices, tet_v, tets, boundary)
    except ValueError as err:
        raise InputError(f"{name}: embedding failed: {err}") from None
    seconds["embed"] = time.perf_counter() - clock

    clock = time.perf_counter()
    say(f"{name}: distance field at {len(tet_v)} tet vertices")
    depth, grad = distance_field(tet_v, unit.vertices, unit.faces)
    lattice = face_lattice(tet_v, boundary).reshape(-1, 3)
    face_depth = distance_field(lattice, unit.vertices, unit.faces)[0].reshape(len(boundary), LATTICE_POINTS)
    seconds["distance"] = time.perf_counter() - clock

    clock = time.perf_counter()
    dense_to_coarse, coarse_to_dense = hausdorff(unit.vertices, unit.faces, coarse_v, coarse_f)
    seconds["hausdorff"] = time.perf_counter() - clock

    stats = _build_stats(
        unit, scale, (coarse_v, coarse_f, tet_v, tets), (embed_tet, embed_bary, depth), quality, sized,
        (index, failures, dense_pairs, dense_to_coarse, coarse_to_dense),
    )  # fmt: skip
    stats.update({f"seconds_{stage}": value for stage, value in seconds.items()})
    arrays = {
        "coarse_vertices": coarse_v * scale + center,
        "coarse_faces": coarse_f,
        "boundary_faces": boundary,
        "tet_vertices": tet_v * scale + center,
        "tets": tets,
        "embed_tet": embed_tet.astype(np.int32),
        "embed_bary": embed_bary,
        "vertex_depth": depth * scale,
        "vertex_grad": grad,
        "face_depth": face_depth * scale,
    }
    return arrays, stats


def _build_stats(
    unit: Surface,
    scale: float,
    meshes: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    embedded: tuple[np.ndarray, np.ndarray, np.ndarray],
    quality: dict,
    sized: dict,
    outcome: tuple[int, list[str], int, float, float],
) -> dict[str, float | int | str]:
    """Return :func:`_build`'s statistics in the caller's units.

    The rung, the meshes' sizes and quality, the sizing, the Hausdorff distances and how well the embedding
    rebuilds the dense vertices.
    """
    coarse_v, coarse_f, tet_v, tets = meshes
    embed_tet, embed_bary, depth = embedded
    index, failures, dense_pairs, dense_to_coarse, coarse_to_dense = outcome
    rebuilt = np.einsum("nk,nkj->nj", embed_bary, tet_v[tets[embed_tet]])
    stats: dict[str, float | int | str] = {
        "rung": f"{index + 1} ({LADDER[index].label})",
        "failed_rungs": " ".join(failures) or "none",
        "dense_intersecting_pairs": dense_pairs,
        "coarse_vertices": len(coarse_v),
        "coarse_faces": len(coarse_f),
        "tets": len(tets),
        "tet_vertices": len(tet_v),
        **quality,
        "maxh_absolute": quality["maxh_absolute"] * scale,
        "cage_offset": quality["cage_offset"] * scale,
        "cage_outside_max": quality["cage_outside_max"] * scale,
        "hausdorff": max(dense_to_coarse, coarse_to_dense) * scale,
        "hausdorff_relative": max(dense_to_coarse, coarse_to_dense),
        "hausdorff_dense_to_coarse": dense_to_coarse * scale,
        "hausdorff_coarse_to_dense": coarse_to_dense * scale,
        "embedding_coverage": float(np.mean(embed_bary.min(axis=1) >= -INSIDE_EPS)),
        "embedding_outside_max": float(outside_distance(tet_v, tets, embed_tet, embed_bary).max(initial=0.0)) * scale,
        "embedding_max_error": float(np.abs(rebuilt - unit.vertices).max()),
        "max_depth": float(depth.max()) * scale,
        **sized,
    }
    if sized:
        stats["thickness"] = sized["thickness_relative"] * scale
    return stats


def default_cache_dir() -> Path:
    """The preprocessing cache: $WARPFEM_CACHE, else $XDG_CACHE_HOME/warpfem, else ~/.cache/warpfem."""
    if os.environ.get("WARPFEM_CACHE"):
        return Path(os.environ["WARPFEM_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "warpfem"


def prepare(
    mesh: str | Path,
    faces: int,
    subdivide: int = 0,
    maxh: float = 0.2,
    cache_dir: Path | None = None,
    timeout_s: float = 120.0,
    progress: Callable[[str], None] | None = None,
    budget_s: float | None = BUDGET_S,
    shells: str | int = "merge",
    max_hole: float | None = None,
    prim: str | None = None,
    across: float = 0.0,
    max_tets: int = DEFAULT_MAX_TETS,
) -> PreparedBody:
    """Preprocess one body, or load it from the cache.

    Args:
        mesh: Surface mesh file (OBJ, PLY, STL, OFF) or ``"builtin:bunny"``.
        faces: Target face count of the simplified (coarse) surface.
        subdivide: Loop subdivision rounds applied to the dense surface after loading.
        maxh: Largest tet edge, as a fraction of the coarse surface's bounding-box diagonal.
        cache_dir: Folder of cached results (``<sha256>.npz``), or None for no caching.
        timeout_s: Time limit of each child-process stage (QEM, outer surface, remeshing, Netgen), in seconds.
        progress: Receives one-line status messages.
        budget_s: Time budget of the whole preparation, in seconds (None: unbounded): no rung of the
            ladder starts after it, each stage's limit is cut to what is left, and Netgen's to
            :data:`NETGEN_SHARE` of that.
        shells: What to do with several shells: ``"merge"`` them into one body, keep the ``"largest"``,
            ``"error"``, or an int k to keep the k-th largest (one body per shell: prepare each k).
        max_hole: Largest hole closed automatically, relative to the bounding-box diagonal (None: the
            default :data:`warpfem.prep.repair.MAX_HOLE_FRACTION`; 0: none).
        prim: For a USD file, the ``UsdGeom.Mesh`` prim's path (None: the file's only mesh).
        across: Tets across the body's thickness (:mod:`warpfem.prep.sizing`): Netgen's size and the coarse
            face count are chosen to put this many over it, within ``max_tets``; ``maxh`` stays the upper
            bound of the size and ``faces`` the lower bound of the count. 0: ``faces`` and ``maxh`` alone.
        max_tets: The tet budget of sizing by thickness (about this many tets at most; ignored at 0 across).

    Returns:
        The prepared body. ``stats`` holds: ``mesh``, ``repairs``, ``cache`` (hit, miss or off), ``rung`` (the ladder
        rung that succeeded), ``failed_rungs`` (the reasons of those before it), ``dense_vertices``, ``dense_faces``,
        ``dense_intersecting_pairs``, ``coarse_vertices``, ``coarse_faces``, ``tets``, ``tet_vertices``,
        ``tet_min_dihedral_deg``, ``tet_min_radius_ratio`` (3 inradius / circumradius, 1 for a regular tet),
        ``volume_ratio`` (coarse / dense volume, or / outer-surface volume for self-intersecting input or overlapping
        shells), ``cage_volume_ratio`` (the cage's), ``cage_offset``, ``cage_outside`` and ``cage_outside_max``
        (:func:`~warpfem.prep.cage.enclose`; lengths in mesh units), ``maxh_absolute`` (mesh units), ``hausdorff``
        (two-sided, sample-based, mesh units; also ``hausdorff_relative`` to the bounding-box diagonal and each
        one-sided value), ``embedding_coverage`` (fraction of dense vertices inside a tet), ``embedding_outside_max``
        (the farthest the others lie outside theirs, mesh units), ``embedding_max_error`` (max
        reconstruction error / bbox diagonal), ``max_depth`` (the deepest tet vertex below the coarse surface, mesh
        units), with ``across``: ``thickness`` (mesh units; ``thickness_relative`` to the diagonal), ``tets_across``,
        ``max_tets`` and ``sizing_capped`` (1 if the budget set the size), and ``seconds_<stage>`` for load, validate,
        sizing, outer and remesh (if used), simplify, tetrahedralize, embed, distance, hausdorff (on a cache hit, those
        of the run that filled the cache, plus ``seconds_cache_read``).

    Raises:
        InputError: For a bad mesh or parameter, or when a stage fails on this mesh (one line).
    """
    say = progress or (lambda _message: None)
    started = time.perf_counter()
    _check_prepare(mesh, faces, maxh, budget_s, across, max_tets)
    clock = time.perf_counter()
    say(f"{mesh}: loading")
    options = f"shells={shells!r} max_hole={max_hole!r}" + (f" prim={prim!r}" if prim is not None else "")
    if across:
        options += f" sizing=v{SIZING_FORMAT} across={across!r} max_tets={max_tets}"
    index = None
    if cache_dir is not None:
        index = _source_index(cache_dir, mesh, f"faces={faces} subdivide={subdivide} maxh={maxh!r} {options}")
        found = _read_indexed(index)
        if found is not None:
            return _hit(found[1], mesh, found[0], say, seconds_load=0.0, clock=clock)
    surface = load_surface(mesh, max_hole=max_hole, shells=shells, prim=prim)
    seconds_load = time.perf_counter() - clock

    path = None
    if cache_dir is not None:
        path = Path(cache_dir) / f"{cache_key(surface, faces, subdivide, maxh, options)}.npz"
        clock = time.perf_counter()
        cached = _read_cache(path)
        if cached is not None:
            _remember(index, path)
            return _hit(cached, mesh, path, say, seconds_load, clock)

    clock = time.perf_counter()
    dense = subdivide_surface(surface, subdivide)
    seconds_load += time.perf_counter() - clock
    deadline = started + budget_s if budget_s is not None else float("inf")
    arrays, built = _build(dense, faces, maxh, timeout_s, deadline, say, (across, max_tets))
    stats: dict[str, float | int | str] = {
        "mesh": str(mesh),
        "repairs": "; ".join(dense.repairs) or "none",
        "cache": "off" if path is None else "miss",
        "dense_vertices": len(dense.vertices),
        "dense_faces": len(dense.faces),
        "seconds_load": seconds_load,
        **built,
    }
    body = PreparedBody(dense_vertices=dense.vertices, dense_faces=dense.faces, **arrays, stats=stats)
    if path is not None:
        _write_cache(path, body)
        _remember(index, path)
    return body


def _check_prepare(
    mesh: str | Path, faces: int, maxh: float, budget_s: float | None, across: float, max_tets: int
) -> None:
    """Raise InputError (one line, naming the mesh) for a parameter :func:`prepare` cannot work with."""
    if budget_s is not None and not budget_s > 0:
        raise InputError(f"{mesh}: budget_s must be positive, got {budget_s}")
    if faces < 4:
        raise InputError(f"{mesh}: faces must be >= 4, got {faces}")
    if not maxh > 0:
        raise InputError(f"{mesh}: maxh must be positive, got {maxh}")
    if not (0 <= across < float("inf")) or (across and max_tets < 1):
        raise InputError(f"{mesh}: across must be >= 0 and finite and max_tets >= 1, got {across} and {max_tets}")


def _hit(
    body: PreparedBody, mesh: str | Path, path: Path, say: Callable[[str], None], seconds_load: float, clock: float
) -> PreparedBody:
    """A body read from the cache file ``path``, its stats saying so (``clock``: when reading began)."""
    say(f"{mesh}: loaded from cache {path}")
    body.stats.update(
        mesh=str(mesh), cache="hit", seconds_load=seconds_load, seconds_cache_read=time.perf_counter() - clock
    )
    return body


def _remember(index: Path | None, path: Path) -> None:
    """Point the index entry ``index`` (if any) at the cache file ``path``."""
    if index is not None:
        _save_atomically(index, lambda stream: stream.write(path.stem.encode()))

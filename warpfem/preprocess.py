"""Preprocessing of one body: load, simplify, tetrahedralize, embed, distance field; with a disk cache.

Everything is in the mesh file's own coordinates; the simulator applies the scene's uniform scale,
rotation and translation afterwards. The cache is content-addressed: a file is named by the sha256 of
the welded input mesh and the parameters, so an edited mesh or changed parameter never hits a stale
entry, and a damaged entry is rebuilt.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from warpfem.embedding import embed
from warpfem.errors import InputError
from warpfem.surface import Surface, load_surface, subdivide_surface

CACHE_FORMAT = 1
"""Version of the cache file layout and of the preprocessing algorithm; bump to invalidate old entries."""

INSIDE_EPS = 1e-9
"""A dense vertex whose smallest barycentric coordinate is >= -this counts as inside its tet."""

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
    stats: dict[str, float | int | str]


_ARRAY_FIELDS = tuple(f.name for f in fields(PreparedBody) if f.name != "stats")


def cache_key(surface: Surface, faces: int, subdivide: int, maxh: float) -> str:
    """Return the sha256 hex digest naming the cache entry of a welded surface and the parameters.

    Args:
        surface: The loaded, welded surface before subdivision.
        faces: Target coarse face count.
        subdivide: Loop subdivision rounds.
        maxh: Relative maximum tet edge length.

    Returns:
        64 hex characters.
    """
    digest = hashlib.sha256()
    digest.update(f"warpfem-prepare v{CACHE_FORMAT} faces={faces} subdivide={subdivide} maxh={maxh!r}\n".encode())
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
    except Exception:  # a damaged file can fail in zipfile, numpy or the OS layer: rebuild it
        return None
    n, p = len(arrays["dense_vertices"]), len(arrays["tet_vertices"])
    consistent = (
        arrays["embed_tet"].shape == (n,)
        and arrays["embed_bary"].shape == (n, 4)
        and arrays["vertex_depth"].shape == (p,)
        and arrays["vertex_grad"].shape == (p, 3)
        and arrays["tets"].ndim == 2
        and arrays["tets"].shape[1:] == (4,)
    )
    return PreparedBody(**arrays, stats=stats) if consistent else None


def _write_cache(path: Path, body: PreparedBody) -> None:
    """Write ``body`` to ``path`` atomically (temporary file in the same folder, then rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {name: getattr(body, name) for name in _ARRAY_FIELDS}
    payload.update({_STAT_PREFIX + key: np.array(value) for key, value in body.stats.items()})
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.stem + ".", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as stream:
            np.savez(stream, **payload)
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise


def _build(
    dense: Surface, faces: int, maxh: float, timeout_s: float, say: Callable[[str], None]
) -> tuple[dict[str, np.ndarray], dict[str, float | int | str]]:
    """Run simplify, tetrahedralize, embed and distance; return the arrays and their stats."""
    from warpfem.distance import distance_field
    from warpfem.simplify import simplify
    from warpfem.tetmesh import tetrahedralize

    name = dense.source
    stats: dict[str, float | int | str] = {}
    clock = time.perf_counter()
    say(f"{name}: simplifying {len(dense.faces)} faces to {faces}")
    coarse_v, coarse_f = simplify(dense.vertices, dense.faces, faces, name=name)
    stats["seconds_simplify"] = time.perf_counter() - clock

    clock = time.perf_counter()
    diag = float(np.linalg.norm(coarse_v.max(axis=0) - coarse_v.min(axis=0)))
    say(f"{name}: tetrahedralizing {len(coarse_f)} faces (maxh {maxh * diag:.4g})")
    tet_v, tets = tetrahedralize(coarse_v, coarse_f, maxh * diag, timeout_s=timeout_s, name=name)
    stats["seconds_tetrahedralize"] = time.perf_counter() - clock

    # tetrahedralize keeps the surface points first and unchanged, so the coarse faces index tet_v as is
    boundary = coarse_f.copy()
    clock = time.perf_counter()
    say(f"{name}: embedding {len(dense.vertices)} dense vertices in {len(tets)} tets")
    embed_tet, embed_bary = embed(dense.vertices, tet_v, tets, boundary)
    stats["seconds_embed"] = time.perf_counter() - clock

    clock = time.perf_counter()
    say(f"{name}: distance field at {len(tet_v)} tet vertices")
    depth, grad = distance_field(tet_v, coarse_v, coarse_f)
    stats["seconds_distance"] = time.perf_counter() - clock

    rebuilt = np.einsum("nk,nkj->nj", embed_bary, tet_v[tets[embed_tet]])
    dense_diag = float(np.linalg.norm(dense.vertices.max(axis=0) - dense.vertices.min(axis=0)))
    stats.update(
        coarse_vertices=len(coarse_v),
        coarse_faces=len(coarse_f),
        tets=len(tets),
        tet_vertices=len(tet_v),
        maxh_absolute=maxh * diag,
        embedding_coverage=float(np.mean(embed_bary.min(axis=1) >= -INSIDE_EPS)),
        embedding_max_error=float(np.abs(rebuilt - dense.vertices).max() / dense_diag),
        max_depth=float(depth.max()),
    )
    arrays = {
        "coarse_vertices": coarse_v,
        "coarse_faces": coarse_f,
        "boundary_faces": boundary,
        "tet_vertices": tet_v,
        "tets": tets,
        "embed_tet": embed_tet.astype(np.int32),
        "embed_bary": embed_bary,
        "vertex_depth": depth,
        "vertex_grad": grad,
    }
    return arrays, stats


def prepare(
    mesh: str | Path,
    faces: int,
    subdivide: int = 0,
    maxh: float = 0.2,
    cache_dir: Path | None = None,
    timeout_s: float = 120.0,
    progress: Callable[[str], None] | None = None,
) -> PreparedBody:
    """Preprocess one body, or load it from the cache.

    Args:
        mesh: Surface mesh file (OBJ, PLY, STL, OFF) or ``"builtin:bunny"``.
        faces: Target face count of the simplified (coarse) surface.
        subdivide: Loop subdivision rounds applied to the dense surface after loading.
        maxh: Largest tet edge, as a fraction of the coarse surface's bounding-box diagonal.
        cache_dir: Folder of cached results (``<sha256>.npz``), or None for no caching.
        timeout_s: Time limit for Netgen, in seconds.
        progress: Receives one-line status messages.

    Returns:
        The prepared body. ``stats`` holds: ``mesh``, ``repairs``, ``cache`` (hit, miss or off),
        ``dense_vertices``, ``dense_faces``, ``coarse_vertices``, ``coarse_faces``, ``tets``,
        ``tet_vertices``, ``maxh_absolute`` (mesh units), ``embedding_coverage`` (fraction of dense
        vertices inside a tet), ``embedding_max_error`` (max reconstruction error / bbox diagonal),
        ``max_depth`` and ``seconds_<stage>`` for load, simplify, tetrahedralize, embed, distance (on a
        cache hit, those of the run that filled the cache, plus ``seconds_cache_read``).

    Raises:
        InputError: For a bad mesh or parameter, or when a stage fails on this mesh (one line).
    """
    say = progress or (lambda _message: None)
    if faces < 4:
        raise InputError(f"{mesh}: faces must be >= 4, got {faces}")
    if not maxh > 0:
        raise InputError(f"{mesh}: maxh must be positive, got {maxh}")
    clock = time.perf_counter()
    say(f"{mesh}: loading")
    surface = load_surface(mesh)
    seconds_load = time.perf_counter() - clock

    path = None
    if cache_dir is not None:
        path = Path(cache_dir) / f"{cache_key(surface, faces, subdivide, maxh)}.npz"
        clock = time.perf_counter()
        cached = _read_cache(path)
        if cached is not None:
            say(f"{mesh}: loaded from cache {path}")
            cached.stats.update(
                mesh=str(mesh), cache="hit", seconds_load=seconds_load, seconds_cache_read=time.perf_counter() - clock
            )
            return cached

    clock = time.perf_counter()
    dense = subdivide_surface(surface, subdivide)
    seconds_load += time.perf_counter() - clock
    arrays, built = _build(dense, faces, maxh, timeout_s, say)
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
    return body

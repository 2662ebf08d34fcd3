"""Which dense vertices collide: collision samples that cover the surface, and the skin the static colliders use.

Chosen once per distinct mesh and spacing and cached beside the prepared body under a key of their own (this
module's source among it), so a change here never prepares a body again.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from warpfem.prep.surface import vertex_normals

DEFAULT_SPACING = 0.016
"""Collision samples of a dense surface about this fraction of the body's bounding-box diagonal apart, when
the scene sets no spacing: every dense vertex lies within half of it of a sample, so two surfaces pressed
together bulge past each other's samples by little (docs/decisions.md)."""

SKIN_SPACING = 0.02
"""The skin's coarser grid, a fraction of the size, when the scene sets no collision spacing (the skin also
takes every vertex of a grid of half of it, then refines)."""

SKIN_TOLERANCE = 0.0002
"""The static colliders act on dense vertices chosen so that none of the others sticks out past its nearest
chosen ones, along its own normal, by more than this fraction of the body's size: between them a resting
dense surface dips at most this far below what the ground holds (docs/decisions.md)."""

SKIN_ROUNDS = 8
"""Refinement rounds of the skin and collision samples (each adds the vertices that stick out most, a few per
cell)."""

FACE_STEP = 0.8
"""Step of the lattice of candidate points on a dense triangle longer than it along an edge, as a share of the
collision spacing (:func:`face_cover`). A low-poly surface (a box of twelve triangles) otherwise collides at
its corners only, and two such bodies pass through each other edge first; a coarse scan's large triangles
leave gaps between its vertices too."""

COLLISION_TOLERANCE = 0.001
"""The collision samples are refined until no dense vertex sticks out past its nearest ones, along its own
normal, by more than this fraction of the body's size (docs/decisions.md)."""


def spacings(collision_spacing: float, size: float) -> tuple[float, float]:
    """The collision samples' spacing and the skin's grid for a body of ``size``, in the same units.

    A scene's ``collision_spacing`` sets both; 0 takes :data:`DEFAULT_SPACING` and :data:`SKIN_SPACING` of the size.
    """
    if collision_spacing:
        return collision_spacing, collision_spacing
    return DEFAULT_SPACING * size, SKIN_SPACING * size


@dataclass(frozen=True)
class SurfaceSamples:
    """Dense vertices chosen to collide, as indices into the dense mesh.

    Attributes:
        collision: (c,) the points tested against other bodies: a cover of the surface, refined at tips.
        skin: (s,) the points the static colliders act on (the grid's, refined where the surface curves).
        face: (k,) dense triangles that carry collision points of their own (those larger than the spacing).
        face_bary: (k, 3) each such point's weights on its triangle's corners.
    """

    collision: np.ndarray
    skin: np.ndarray
    face: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    face_bary: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


def grid_picks(positions: np.ndarray, spacing: float) -> np.ndarray:
    """One vertex per occupied cell of a grid of ``spacing`` (the first in index order), sorted indices."""
    cell = np.floor((positions - positions.min(axis=0)) / spacing).astype(np.int64)
    _, pick = np.unique(cell, axis=0, return_index=True)
    return np.sort(pick)


def covering_picks(positions: np.ndarray, radius: float) -> np.ndarray:
    """Vertices chosen so that every vertex lies within ``radius`` of one and no two lie closer (sorted indices).

    Greedy in index order. For the same count it leaves a vertex about half as far from its nearest pick as
    one vertex per grid cell does, since a grid picks whatever vertex comes first in a cell.
    """
    from scipy.spatial import cKDTree

    x = np.asarray(positions, np.float64)
    tree, covered, picks = cKDTree(x), np.zeros(len(x), bool), []
    for i in range(len(x)):
        if not covered[i]:
            picks.append(i)
            covered[tree.query_ball_point(x[i], radius)] = True
    return np.asarray(picks, np.int64)


def surface_samples(
    positions: np.ndarray, faces: np.ndarray, spacing: float, tolerance: float, skin_spacing: float | None = None
) -> SurfaceSamples:
    """Collision samples about ``spacing`` (m) apart and the skin, each refined.

    The collision samples cover the surface (every dense vertex within half of ``spacing`` of one,
    :func:`covering_picks`), then are refined (:func:`refined`) to :data:`COLLISION_TOLERANCE` of the size: a
    tip or an edge between them (an ear, a finger, a thin bar's corner) would otherwise sink into another
    body unseen. Where triangles are larger than that, points on them fill the gaps (:func:`face_cover`). The
    skin, for the static colliders, takes a grid every ``skin_spacing`` (default: ``spacing``) refined to the
    collision tolerance and a grid every half of it, refined to ``tolerance`` (m); its denser grid bounds how
    far a dense vertex lies from a skin point, so a tilted patch between them dips less.
    """
    x = np.asarray(positions, np.float64)
    normal = vertex_normals(x, faces)
    size = float(np.linalg.norm(x.max(axis=0) - x.min(axis=0)))
    grid = skin_spacing or spacing
    collision = refined(x, normal, covering_picks(x, spacing / 2.0), spacing, COLLISION_TOLERANCE * size)
    coarse = refined(x, normal, grid_picks(x, grid), grid, COLLISION_TOLERANCE * size)
    skin = refined(x, normal, np.union1d(coarse, grid_picks(x, grid / 2.0)), grid, tolerance)
    face, face_bary = face_cover(x, faces, collision, spacing)
    return SurfaceSamples(collision, skin, face, face_bary)


def face_cover(x: np.ndarray, faces: np.ndarray, picks: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Points on the dense triangles where the vertex ``picks`` leave holes in the surface's cover.

    Of :func:`face_lattice`'s points every ``FACE_STEP`` of ``spacing``, those farther than ``spacing`` from
    every pick, thinned to a cover of their own at that radius: no point of the surface then lies much farther
    than the spacing from a collision point, and a scan whose vertices already cover it gets few or none
    (docs/decisions.md, "Collision points on large triangles").
    """
    from scipy.spatial import cKDTree

    face, bary = face_lattice(x, faces, FACE_STEP * spacing)
    if len(face) == 0:
        return face, bary
    points = np.einsum("kj,kjd->kd", bary, x[np.asarray(faces, np.int64)[face]])
    gap, _ = cKDTree(x[picks]).query(points)
    far = np.flatnonzero(gap > spacing)
    keep = far[covering_picks(points[far], spacing)] if len(far) else far
    return face[keep], bary[keep]


def face_lattice(positions: np.ndarray, faces: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Points on the triangles with an edge longer than ``step``: a lattice about ``step`` apart on each.

    A triangle whose longest edge is L gets the nodes of its split into ceil(L / step)^2 similar triangles,
    its own corners (dense vertices) left out; a point on an edge two such triangles share is kept once.

    Returns:
        ``(face, bary)``: (k,) int32 triangle of each point and (k, 3) weights on its corners.
    """
    x = np.asarray(positions, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    empty = np.zeros(0, np.int32), np.zeros((0, 3))
    if len(f) == 0 or step <= 0:
        return empty
    corners = x[f]
    longest = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max(axis=1)
    splits = np.ceil(longest / step).astype(np.int64)
    chosen_face, chosen_bary = [], []
    for n in np.unique(splits[splits > 1]):
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        keep = (i + j <= n) & ~(((i == 0) | (j == 0)) & ((i + j == 0) | (i + j == n)))
        bary = np.stack([n - i[keep] - j[keep], i[keep], j[keep]], axis=1) / n
        these = np.flatnonzero(splits == n)
        chosen_face.append(np.repeat(these, len(bary)))
        chosen_bary.append(np.tile(bary, (len(these), 1)))
    if not chosen_face:
        return empty
    face, bary = np.concatenate(chosen_face), np.concatenate(chosen_bary)
    points = np.einsum("kj,kjd->kd", bary, x[f[face]])
    _, first = np.unique(np.round(points / (1e-3 * step)).astype(np.int64), axis=0, return_index=True)
    first.sort()
    return face[first].astype(np.int32), bary[first]


def refined(x: np.ndarray, normal: np.ndarray, chosen: np.ndarray, spacing: float, tolerance: float) -> np.ndarray:
    """``chosen`` vertices of ``x`` (with unit normals ``normal``) plus those that stick out past them.

    A vertex sticks out past the chosen ones by ``min (v - s) . n_v`` over its nearest chosen ``s``; each of
    :data:`SKIN_ROUNDS` rounds adds, per cell of a quarter of ``spacing``, the vertex that sticks out most past
    ``tolerance`` (m).
    """
    from scipy.spatial import cKDTree

    for _ in range(SKIN_ROUNDS):
        at = x[chosen]
        _, near = cKDTree(at).query(x, k=min(8, len(chosen)), workers=-1)
        out = stick_out(x, normal, at, near.reshape(len(x), -1))
        bad = np.flatnonzero(out > tolerance)
        if len(bad) == 0:
            break
        order = bad[np.argsort(-out[bad])]
        cell = np.floor((x[order] - x.min(axis=0)) / (spacing / 4.0)).astype(np.int64)
        _, first = np.unique(cell, axis=0, return_index=True)
        chosen = np.union1d(chosen, order[first])
    return chosen


STICK_OUT_ROWS = 1 << 15
"""Vertices :func:`stick_out` takes at a time, so its (rows, 8, 3) temporaries stay a few MB."""


def stick_out(x: np.ndarray, normal: np.ndarray, chosen: np.ndarray, near: np.ndarray) -> np.ndarray:
    """Per vertex, ``min (x_v - s) . n_v`` over its nearest chosen points ``s = chosen[near[v]]`` (m)."""
    out = np.empty(len(x))
    for a in range(0, len(x), STICK_OUT_ROWS):
        b = a + STICK_OUT_ROWS
        out[a:b] = np.einsum("vkj,vj->vk", x[a:b, None, :] - chosen[near[a:b]], normal[a:b]).min(axis=1)
    return out

"""Scene defaults applied to the document: quality presets, and the CG iteration count of fixed mode.

A scene names a preset as ``[solver] quality = "<name>"``; :mod:`warpfem.scene` applies both.
"""

from __future__ import annotations

from typing import Any

PRESETS: dict[str, dict[str, object]] = {
    "preview": dict(
        substeps=1,
        cg_mode="fixed",
        cg_iterations=10,
        cg_tolerance=1e-4,
        faces=250,
        maxh=0.3,
        tets_across=0.0,
        max_tets=50000,
        elements="linear",
    ),
    "default": dict(
        substeps=2,
        cg_mode="tolerance",
        cg_iterations=400,
        cg_tolerance=1e-3,
        faces=1000,
        maxh=0.2,
        tets_across=2.0,
        max_tets=3000,
        elements="quadratic",
    ),
    "high": dict(
        substeps=8,
        cg_mode="tolerance",
        cg_iterations=1000,
        cg_tolerance=1e-5,
        faces=2000,
        maxh=0.15,
        tets_across=4.0,
        max_tets=8000,
        elements="quadratic",
    ),
}
"""Defaults for the scene's ``substeps``, the solver's ``cg_mode``, ``cg_iterations``, ``cg_tolerance`` and
``elements``, and each object's ``faces``, ``maxh``, ``tets_across`` and ``max_tets``; keys the scene file sets
itself win. Each is a measured point: its cost and its error on a dense cantilever through the whole pipeline
are in docs/tradeoff.md."""

FIXED_CG_ITERATIONS = 100
"""CG's iteration count in ``cg_mode = "fixed"`` where the scene gives none (``cg_iterations``' default, 400, is
a cap meant for tolerance mode, which a converging solve never reaches)."""

APPROACH_LIMIT = 0.03
"""The most two bodies may close on each other in one step by default, as a share of the smaller one's size,
before a frame runs more substeps (``[collision] approach_limit``). Chosen by measurement (docs/decisions.md,
"Frames of fast approach at twice the substeps", "The approach limit at 3 % with lifted collision points")."""

CONTACT_DAMPING = 20.0
"""The damping of a contact between bodies that closes fast, as a ratio to critical for its point's mass on its
penalty spring (``[collision] damping``). Chosen by measurement (docs/decisions.md, "A damper on contacts that
close fast")."""

CONTACT_OFFSET = 0.004
"""How far outside another body's dense surface a contact with it starts by default, as a share of the scene's
smallest colliding body's size (``[collision] offset``): the body-body counterpart of :data:`STATIC_OFFSET`.
Chosen by measurement (docs/decisions.md, "Body-body contacts from an offset", "The contact offset at 0.4 %")."""

CONTACT_OFFSET_LIMIT = 0.05
"""The contact offset must lie below this share of the size (``[collision] offset``, ``CollisionSettings``)."""

STATIC_OFFSET = 8.0e-4
"""How far above a static collider's surface (the ground, an obstacle) its penalty starts by default, as a share of
the touching body's size (its tet mesh's rest bounding-box diagonal): a penalty holds a load at some depth, and
this gap takes that depth instead of the visible surface; a body that gives nothing floats under 0.1 % of its
visible size above the collider. Chosen by measurement (docs/decisions.md, "Static contacts from an
offset")."""

STATIC_OFFSET_LIMIT = 0.05
"""A static collider's offset must not exceed this share of the size (``[ground] offset``, obstacles, ``Ground``)."""


def apply_mode_default(doc: dict[str, Any]) -> None:
    """Give a scene document's fixed-mode solver without ``cg_iterations`` :data:`FIXED_CG_ITERATIONS`."""
    solver = doc.get("solver")
    if isinstance(solver, dict) and solver.get("cg_mode") == "fixed":
        solver.setdefault("cg_iterations", FIXED_CG_ITERATIONS)

"""The quality presets a scene names as ``[solver] quality = "<name>"`` (applied by :mod:`warpfem.scene`)."""

from __future__ import annotations

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

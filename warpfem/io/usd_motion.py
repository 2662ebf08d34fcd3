"""Reading an animated prim's rigid motion from a USD file (what a ``[[handle]]`` with ``usd`` follows)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from warpfem.errors import InputError

RIGID_TOLERANCE = 1.0e-4
"""How far a relative transform's linear part may be from a rotation (max entry of L^T L - I) and still count as one."""


def read_motion(path: str | Path, prim: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The world transform of ``prim`` over time, relative to its transform at time code 0, as rigid keys.

    Sampled at every authored time sample of the prim and its ancestors at or after time code 0 and at every
    whole time code between them; times in seconds at the stage's ``timeCodesPerSecond``, translations in
    metres (the stage's ``metersPerUnit``). A point at ``x`` at time 0 is at ``R x + T`` later.

    Returns:
        times (k,) s, rotations (k, 3, 3), translations (k, 3) m.

    Raises:
        InputError: An unreadable stage, a prim that is missing or not transformable, or a transform that
            scales or shears relative to time 0 (one line naming the file and what is wrong).
    """
    from pxr import Tf, Usd, UsdGeom

    try:
        stage = Usd.Stage.Open(str(path))
    except Tf.ErrorException as exc:
        raise InputError(f"{path}: unreadable USD file ({str(exc).strip().splitlines()[-1]})") from None
    found = stage.GetPrimAtPath(prim) if _prim_path_ok(prim) else None
    if not found or not found.IsValid():
        raise InputError(f"{path}: no prim {prim}")
    if not found.IsA(UsdGeom.Xformable):
        raise InputError(f"{path}: prim {prim} is not transformable (a {found.GetTypeName() or 'typeless prim'})")
    codes = set()
    walk = found
    while walk and walk.IsValid() and not walk.IsPseudoRoot():
        if walk.IsA(UsdGeom.Xformable):
            codes.update(UsdGeom.Xformable(walk).GetTimeSamples())
        walk = walk.GetParent()
    codes = sorted(c for c in codes if c >= 0.0)
    if codes:
        codes = sorted(set(codes) | set(np.arange(np.ceil(codes[0]), codes[-1]).tolist()) | {0.0})
    else:
        codes = [0.0]
    xform = UsdGeom.Xformable(found)
    world = [np.asarray(xform.ComputeLocalToWorldTransform(Usd.TimeCode(c)), np.float64) for c in codes]
    rest_inverse = np.linalg.inv(world[0])
    meters = UsdGeom.GetStageMetersPerUnit(stage)
    rotations, translations = [], []
    for code, w in zip(codes, world, strict=True):
        relative = (rest_inverse @ w).T  # USD's row vectors: a point x0 at time 0 is at x0 W0^-1 W(t)
        linear = relative[:3, :3]
        if np.abs(linear.T @ linear - np.eye(3)).max() > RIGID_TOLERANCE or np.linalg.det(linear) < 0:
            raise InputError(
                f"{path}: prim {prim} scales, shears or mirrors at time code {code:g} (relative to time 0); "
                "a handle follows rigid motion only"
            )
        rotations.append(linear)
        translations.append(relative[:3, 3] * meters)
    seconds = np.asarray(codes, np.float64) / stage.GetTimeCodesPerSecond()
    return seconds, np.asarray(rotations), np.asarray(translations)


def _prim_path_ok(prim: str) -> bool:
    """Whether ``prim`` is a valid absolute prim path."""
    from pxr import Sdf

    return Sdf.Path.IsValidPathString(prim) and Sdf.Path(prim).IsAbsolutePath()

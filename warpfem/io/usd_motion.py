"""Reading an animated prim's rigid motion from a USD file (what a ``[[handle]]`` with ``usd`` follows)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from warpfem.errors import InputError

RIGID_TOLERANCE = 1.0e-4
"""How far a relative transform's linear part may be from a rotation (max entry of L^T L - I) and still count as one."""


def read_motion(path: str | Path, prim: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The world transform of ``prim`` over time, relative to its transform at time code 0, as rigid keys.

    Sampled at every authored time sample of the prim and its ancestors at or after time code 0 and at every
    whole time code between them; times in seconds at the stage's ``timeCodesPerSecond``, translations in
    metres (the stage's ``metersPerUnit``). A point at ``x`` at time 0 is at ``R x + T`` later.

    Returns:
        times (k,) s, rotations (k, 3, 3), translations (k, 3) m, and the prim's origin at time 0 (3,) m, the
        pivot about which to interpolate between samples.

    Raises:
        InputError: An unreadable stage, a prim that is missing or not transformable, or a transform that
            scales or shears relative to time 0 (one line naming the file and what is wrong).
    """
    from pxr import Usd, UsdGeom

    stage = _open(path)
    found = stage.GetPrimAtPath(prim) if _prim_path_ok(prim) else None
    if not found or not found.IsValid():
        raise InputError(f"{path}: no prim {prim}")
    if not found.IsA(UsdGeom.Xformable):
        raise InputError(f"{path}: prim {prim} is not transformable (a {found.GetTypeName() or 'typeless prim'})")
    codes = _codes(_ancestor_samples(found))
    xform = UsdGeom.Xformable(found)
    world = [np.asarray(xform.ComputeLocalToWorldTransform(Usd.TimeCode(c)), np.float64) for c in codes]
    return _rigid_keys(stage, path, f"prim {prim}", codes, world)


def read_joint_motion(path: str | Path, joint: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The animated world transform of a ``UsdSkel`` joint, ``"/Path/To/Skeleton:joint/path"``, as rigid keys.

    As :func:`read_motion`, sampled at the skeleton animation's time samples and its ancestors' (and every
    whole time code between them), relative to time code 0.

    Raises:
        InputError: An unreadable stage, a path that names no ``Skeleton`` or no joint of it (the message lists
            its joints), or a joint that scales or shears relative to time 0.
    """
    from pxr import UsdGeom, UsdSkel

    stage = _open(path)
    skel_path, _, name = joint.partition(":")
    found = stage.GetPrimAtPath(skel_path) if _prim_path_ok(skel_path) else None
    if not name or not found or not found.IsValid() or not found.IsA(UsdSkel.Skeleton):
        raise InputError(f'{path}: joint {joint!r} is not "/Path/To/Skeleton:joint/path" of a Skeleton prim')
    query = UsdSkel.Cache().GetSkelQuery(UsdSkel.Skeleton(found))
    order = [str(j) for j in query.GetJointOrder()]
    if name not in order:
        raise InputError(f"{path}: skeleton {skel_path} has no joint {name!r} (joints: {', '.join(order)})")
    index = order.index(name)
    samples = set(_ancestor_samples(found))
    if query.GetAnimQuery():
        samples.update(query.GetAnimQuery().GetJointTransformTimeSamples())
    codes = _codes(samples)
    world = [np.asarray(query.ComputeJointWorldTransforms(UsdGeom.XformCache(c))[index], np.float64) for c in codes]
    return _rigid_keys(stage, path, f"joint {joint}", codes, world)


def _open(path: str | Path) -> object:
    """The stage of ``path`` (an :class:`InputError` naming it if unreadable)."""
    from pxr import Tf, Usd

    try:
        return Usd.Stage.Open(str(path))
    except Tf.ErrorException as exc:
        raise InputError(f"{path}: unreadable USD file ({str(exc).strip().splitlines()[-1]})") from None


def _ancestor_samples(prim: object) -> list[float]:
    """The authored transform time samples of ``prim`` and its transformable ancestors."""
    from pxr import UsdGeom

    codes = []
    while prim and prim.IsValid() and not prim.IsPseudoRoot():
        if prim.IsA(UsdGeom.Xformable):
            codes += UsdGeom.Xformable(prim).GetTimeSamples()
        prim = prim.GetParent()
    return codes


def _codes(samples: object) -> list[float]:
    """Time code 0, the samples at or after it and every whole time code between them, sorted."""
    codes = sorted(c for c in set(samples) if c >= 0.0)
    if not codes:
        return [0.0]
    return sorted(set(codes) | set(np.arange(np.ceil(codes[0]), codes[-1]).tolist()) | {0.0})


def _rigid_keys(
    stage: object, path: str | Path, what: str, codes: list[float], world: list[np.ndarray]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The world transforms ``world`` relative to the first, as rigid keys.

    Returns times (s), rotations, translations (m) and the origin of the first transform (m).
    """
    from pxr import UsdGeom

    rest_inverse = np.linalg.inv(world[0])
    meters = UsdGeom.GetStageMetersPerUnit(stage)
    rotations, translations = [], []
    for code, w in zip(codes, world, strict=True):
        relative = (rest_inverse @ w).T  # USD's row vectors: a point x0 at time 0 is at x0 W0^-1 W(t)
        linear = relative[:3, :3]
        if np.abs(linear.T @ linear - np.eye(3)).max() > RIGID_TOLERANCE or np.linalg.det(linear) < 0:
            raise InputError(
                f"{path}: {what} scales, shears or mirrors at time code {code:g} (relative to time 0); "
                "a handle follows rigid motion only"
            )
        rotations.append(linear)
        translations.append(relative[:3, 3] * meters)
    seconds = np.asarray(codes, np.float64) / stage.GetTimeCodesPerSecond()
    return seconds, np.asarray(rotations), np.asarray(translations), world[0][3, :3] * meters


def _prim_path_ok(prim: str) -> bool:
    """Whether ``prim`` is a valid absolute prim path."""
    from pxr import Sdf

    return Sdf.Path.IsValidPathString(prim) and Sdf.Path(prim).IsAbsolutePath()

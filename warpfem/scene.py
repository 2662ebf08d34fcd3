"""Scene files: TOML in, validated configuration dataclasses out.

Every key is documented in ``scenes/README.md``. A problem with a scene file raises
:class:`warpfem.errors.InputError` with one line naming the file, the key (with its table) and
what is wrong, e.g. ``scene.toml: object[0] 'bunny': young must be > 0 Pa, got -5.0``. All quantities
are SI: metres, seconds, kilograms, pascals, degrees for rotations.
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import importlib.resources
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from warpfem.errors import InputError
from warpfem.presets import (
    APPROACH_LIMIT,
    CONTACT_DAMPING,
    CONTACT_OFFSET,
    CONTACT_OFFSET_LIMIT,
    PRESETS,
    STATIC_OFFSET,
    STATIC_OFFSET_LIMIT,
    apply_mode_default,
)
from warpfem.scene_checks import (
    _NAME_RE,
    _check_choice,
    _check_float,
    _check_int,
    _check_range,
    _check_vec3,
    _is_number,
    _object_table,
    _Problem,
    _shown,
    _table,
)

Vec3 = tuple[float, float, float]

#: The mesh value that names the Stanford bunny shipped with Warp instead of a file.
BUILTIN_BUNNY = "builtin:bunny"
BUILTIN_MESHES = (BUILTIN_BUNNY,)


def _apply_preset(doc: dict[str, Any], origin: str) -> None:
    """Fill the keys a ``[solver] quality`` preset sets, where the scene file leaves them unset."""
    solver = doc.get("solver")
    if not isinstance(solver, dict) or "quality" not in solver:
        return
    name = solver["quality"]
    if name not in PRESETS:
        raise InputError(f"{origin}: solver.quality must be one of {', '.join(PRESETS)}, got {_shown(name)}")
    preset = PRESETS[name]
    scene = doc.setdefault("scene", {})
    if isinstance(scene, dict):
        scene.setdefault("substeps", preset["substeps"])
    for key in ("cg_mode", "cg_iterations", "cg_tolerance", "elements"):
        solver.setdefault(key, preset[key])
    for obj in doc.get("object", []) if isinstance(doc.get("object"), list) else []:
        if isinstance(obj, dict):
            for key in ("faces", "maxh", "tets_across", "max_tets"):
                obj.setdefault(key, preset[key])


@dataclass
class SolverConfig:
    """The linear solver of each implicit Euler step (conjugate gradients).

    Attributes:
        cg_mode: ``"tolerance"``: iterate until the relative residual is below ``cg_tolerance`` (at
            most ``cg_iterations``); ``"fixed"``: always ``cg_iterations`` iterations (the paper's
            choice: predictable frame time, less accuracy).
        cg_iterations: The iteration count in fixed mode, the cap in tolerance mode (>= 1). A scene file in
            fixed mode that leaves it out gets :data:`~warpfem.presets.FIXED_CG_ITERATIONS`.
        cg_tolerance: Relative residual ||r|| / ||b|| to stop at in tolerance mode (0 < tol < 1).
        contact_passes: Looks per step for the contacts a solve's answer makes that the step did not count,
            each followed by a solve of the bodies they touch where some were found (>= 0; see
            :class:`~warpfem.sim.solver.Solver`); the first also looks between bodies, the others at the ground
            and obstacles only.
        rotation_updates: Re-linearisations per step at most (>= 0; see :class:`~warpfem.sim.solver.Solver`).
        rotation_tolerance: The turn within a step (rad, >= 0) past which a tet is re-linearised, in a body
            whose tets turned past it on average (the volume average of the turn to the fourth power) or one of
            whose tets turned past twice it.
        elements: ``"linear"`` (4-node) or ``"quadratic"`` (10-node) tets, which bend without locking.
        static_lift: Whether each step ends with the visible surface lifted out of the ground and the still
            obstacles (see :class:`~warpfem.sim.solver.Solver`); false: their penalties alone, as the paper.
        quality: A preset of :data:`PRESETS` whose values fill the keys the scene leaves unset, or None.
    """

    cg_mode: str = "tolerance"
    cg_iterations: int = 400
    cg_tolerance: float = 1e-4
    contact_passes: int = 2
    rotation_updates: int = 2
    rotation_tolerance: float = 0.01
    elements: str = "linear"
    static_lift: bool = True
    quality: str | None = None

    @property
    def stop_tolerance(self) -> float:
        """The relative tolerance CG is given: ``cg_tolerance`` in tolerance mode, 0 (no early stop) in fixed mode."""
        return self.cg_tolerance if self.cg_mode == "tolerance" else 0.0

    def validate(self, origin: str = "<scene>") -> None:
        """Raise :class:`InputError` naming ``origin`` (the scene file) on the first bad value."""
        err = _table(origin, "solver")
        _check_choice(err, "cg_mode", self.cg_mode, ("tolerance", "fixed"))
        _check_choice(err, "elements", self.elements, ("linear", "quadratic"))
        _check_int(err, "cg_iterations", self.cg_iterations, 1)
        _check_range(err, "cg_tolerance", self.cg_tolerance, gt=0.0, lt=1.0)
        _check_int(err, "contact_passes", self.contact_passes, 0)
        _check_int(err, "rotation_updates", self.rotation_updates, 0)
        _check_range(err, "rotation_tolerance", self.rotation_tolerance, ge=0.0)
        if not isinstance(self.static_lift, bool):
            raise err("static_lift", f"must be true or false, got {_shown(self.static_lift)}")


@dataclass
class GroundConfig:
    """An infinite ground plane normal to the up axis, acting by a penalty force with friction.

    Attributes:
        enabled: Whether there is a ground at all.
        height: Its position along the up axis (m).
        stiffness: Penalty per unit mass (1/s^2): a vertex at depth d below the ground is pushed
            back with acceleration ``stiffness * d`` (> 0).
        friction: Coulomb friction coefficient (>= 0).
        offset: How far above the plane the penalty starts, as a share of the touching body's size (its tet
            mesh's bounding-box diagonal; 0 <= offset <= 0.05): under load a body rests in this gap rather than
            with its visible surface below the ground.
    """

    enabled: bool = True
    height: float = 0.0
    stiffness: float = 1e7
    friction: float = 0.5
    offset: float = STATIC_OFFSET

    def validate(self, origin: str = "<scene>") -> None:
        """Raise :class:`InputError` naming ``origin`` (the scene file) on the first bad value."""
        err = _table(origin, "ground")
        if not isinstance(self.enabled, bool):
            raise err("enabled", f"must be true or false, got {_shown(self.enabled)}")
        _check_float(err, "height", self.height)
        _check_range(err, "stiffness", self.stiffness, "1/s^2", gt=0.0)
        _check_range(err, "friction", self.friction, ge=0.0)
        _check_range(err, "offset", self.offset, ge=0.0, le=STATIC_OFFSET_LIMIT)


@dataclass
class CollisionConfig:
    """Collisions between bodies (and of a body with itself where the object asks for it).

    Attributes:
        enabled: Whether bodies collide with each other at all (a scene of one body without
            self-collision never runs the collision stage).
        stiffness: Penalty per unit mass (1/s^2): a collision point at depth d inside another body is
            pushed out with acceleration ``stiffness * d`` (> 0).
        friction: Coulomb friction coefficient between bodies (>= 0).
        approach_limit: The most two bodies may close on each other in one step, as a share of the smaller
            one's size (0 <= limit < 1): a frame in which two bodies near each other would close faster runs
            the fewest of 1.25 times the substeps (a multiple of 4), 1.5 times (an even count) or twice that
            brings the closing within the limit, so that thin parts do not pass through each other in a fast
            impact; 0: never.
        offset: How far outside another body's visible surface a contact with it starts, as a share of the
            scene's smallest colliding body's size (0 <= offset < 0.05): the give a penalty needs to hold a
            load goes into that gap instead of into the other body, and bodies resting on each other stand up
            to that far apart; 0: at the surface.
        damping: Damping along the way out of a contact that closes by more than the offset in a step,
            as a ratio to critical for its point's mass on its penalty spring (>= 0): a fast impact is stopped
            nearer the surface, at the cost of some of its bounce; resting and settling contacts, which close
            slower, are left undamped. 0: none.
    """

    enabled: bool = True
    stiffness: float = 1e7
    friction: float = 0.5
    approach_limit: float = APPROACH_LIMIT
    offset: float = CONTACT_OFFSET
    damping: float = CONTACT_DAMPING

    def validate(self, origin: str = "<scene>") -> None:
        """Raise :class:`InputError` naming ``origin`` (the scene file) on the first bad value."""
        err = _table(origin, "collision")
        if not isinstance(self.enabled, bool):
            raise err("enabled", f"must be true or false, got {_shown(self.enabled)}")
        _check_range(err, "stiffness", self.stiffness, "1/s^2", gt=0.0)
        _check_range(err, "friction", self.friction, ge=0.0)
        _check_range(err, "approach_limit", self.approach_limit, ge=0.0, lt=1.0)
        _check_range(err, "offset", self.offset, ge=0.0, lt=CONTACT_OFFSET_LIMIT)
        _check_range(err, "damping", self.damping, ge=0.0)


KEY_COLUMNS = "[t, tx, ty, tz, rx, ry, rz]"
"""One key of a rigid animation: time (s), translation (m), rotation (degrees, about X then Y then Z)."""


def _check_keys(err: _Problem, key: str, keys: object) -> None:
    """A rigid animation's keys: rows of 7 finite numbers, times >= 0 and strictly increasing."""
    if not isinstance(keys, (list, tuple)) or not keys:
        raise err(key, f"must be a non-empty list of {KEY_COLUMNS} rows, got {_shown(keys)}")
    for k, row in enumerate(keys):
        if not isinstance(row, list) or len(row) != 7 or not all(_is_number(v) for v in row):
            raise err(f"{key}[{k}]", f"must be {KEY_COLUMNS} (7 numbers), got {_shown(row)}")
        if not all(math.isfinite(v) for v in row):
            raise err(f"{key}[{k}]", f"must hold finite numbers, got {row}")
        if k == 0 and row[0] < 0:
            raise err(f"{key}[0]", f"time must be >= 0 s, got {row[0]}")
        if k > 0 and row[0] <= keys[k - 1][0]:
            before = f"{key}[{k - 1}]'s {keys[k - 1][0]} s"
            raise err(f"{key}[{k}]", f"time {row[0]} s must be after {before} (times strictly increasing)")


def _check_name(err: _Problem, value: object) -> None:
    if not isinstance(value, str) or not _NAME_RE.fullmatch(value):
        raise err(
            "name",
            "must be a valid USD prim name (letters, digits, underscores, not starting with a "
            f"digit), got {_shown(value)}",
        )


MESH_OBSTACLE_KEYS = ("mesh", "prim", "scale", "rotate", "translate")


@dataclass
class ObstacleConfig:
    """A collider: a sphere, a box or a triangle mesh, acting like the ground (penalty and friction), still or keyed.

    Attributes:
        kind: ``"sphere"``, ``"box"`` or ``"mesh"``.
        center: A sphere's or box's centre (m).
        radius: The sphere's radius (m, > 0; spheres only).
        half_extents: The box's half sizes along x, y, z (m, each > 0; boxes only).
        mesh: A mesh obstacle's file (OBJ, PLY, STL, OFF or USD; absolute once loaded); closed or open.
        prim: For a USD mesh file, the ``UsdGeom.Mesh`` prim to use (default: the file's only mesh).
        scale: Uniform scale of the mesh (> 0; default 1).
        rotate: XYZ Euler angles of the mesh (degrees; default 0).
        translate: Translation of the mesh (m; default 0).
        keys: A rigid animation, rows ``[t, tx, ty, tz, rx, ry, rz]`` (s, m, degrees) about the obstacle's centre
            (a mesh's: the centre of its placed bounding box), or None: it stays.
        stiffness: Penalty per unit mass (1/s^2, > 0).
        friction: Coulomb friction coefficient (>= 0).
        offset: As the ground's: how far out from its surface the penalty starts, a share of the body's size.
        name: Its name in output (default ``obstacle<index>``).
    """

    kind: str
    center: Vec3 | None = None
    radius: float | None = None
    half_extents: Vec3 | None = None
    mesh: str | None = None
    prim: str | None = None
    scale: float | None = None
    rotate: Vec3 | None = None
    translate: Vec3 | None = None
    keys: list | None = None
    stiffness: float = 1e7
    friction: float = 0.5
    offset: float = STATIC_OFFSET
    name: str | None = None

    def validate(self, origin: str = "<scene>", index: int = 0) -> None:
        """Raise :class:`InputError` naming ``origin`` and ``obstacle[index]`` on the first bad value."""
        err = _Problem(origin, f"obstacle[{index}]: ")
        _check_choice(err, "kind", self.kind, ("sphere", "box", "mesh"))
        if self.name is not None:
            _check_name(err, self.name)
        if self.kind == "mesh":
            self._validate_mesh(err)
        else:
            for key in MESH_OBSTACLE_KEYS:
                if getattr(self, key) is not None:
                    raise err(key, 'is for kind = "mesh" obstacles')
            if self.center is None:
                raise err("center", "is required")
            _check_vec3(err, "center", self.center)
        if self.kind == "sphere":
            if self.half_extents is not None:
                raise err("half_extents", "is for boxes; a sphere takes radius")
            if self.radius is None:
                raise err("radius", "is required for a sphere")
            _check_range(err, "radius", self.radius, "m", gt=0.0)
        elif self.kind == "box":
            if self.radius is not None:
                raise err("radius", "is for spheres; a box takes half_extents")
            if self.half_extents is None:
                raise err("half_extents", "is required for a box")
            _check_vec3(err, "half_extents", self.half_extents)
            if min(self.half_extents) <= 0.0:
                raise err("half_extents", f"must all be > 0 m, got {list(self.half_extents)}")
        if self.keys is not None:
            _check_keys(err, "keys", self.keys)
        _check_range(err, "stiffness", self.stiffness, "1/s^2", gt=0.0)
        _check_range(err, "friction", self.friction, ge=0.0)
        _check_range(err, "offset", self.offset, ge=0.0, le=STATIC_OFFSET_LIMIT)

    def _validate_mesh(self, err: _Problem) -> None:
        for key in ("center", "radius", "half_extents"):
            if getattr(self, key) is not None:
                raise err(key, "is for spheres and boxes; a mesh obstacle is placed by scale, rotate and translate")
        if not isinstance(self.mesh, str) or not self.mesh:
            raise err("mesh", f"is required for a mesh obstacle (a file path), got {_shown(self.mesh)}")
        if not Path(self.mesh).is_file():
            raise err("mesh", f"file not found: {self.mesh}")
        if self.prim is not None and (not isinstance(self.prim, str) or not self.prim.startswith("/")):
            raise err("prim", f'must be a prim path such as "/World/Mesh", got {_shown(self.prim)}')
        if self.scale is not None:
            _check_range(err, "scale", self.scale, gt=0.0)
        for key in ("rotate", "translate"):
            if getattr(self, key) is not None:
                _check_vec3(err, key, getattr(self, key))


USD_SUFFIXES = (".usd", ".usda", ".usdc")


@dataclass
class HandleConfig:
    """A region of a body that follows an animation: the tet vertices in a box, held to a rigid motion.

    Attributes:
        object: The body's name.
        min: Lower corner of the box (m, world coordinates at rest).
        max: Upper corner of the box (m).
        keys: Rows ``[t, tx, ty, tz, rx, ry, rz]`` (s, m, degrees about X then Y then Z): a rigid motion about
            the box's centre, linear between keys (rotations by slerp), held after the last; or None.
        usd: A USD file (absolute once loaded) whose animated ``prim`` the vertices follow instead: its world
            transform relative to its transform at time 0; or None.
        prim: The ``UsdGeom.Xformable`` prim of ``usd``.
        joint: Instead of ``prim``, a ``UsdSkel`` joint of ``usd`` as ``"/Path/To/Skeleton:joint/path"``:
            its animated world transform.
        name: Its name in output (default ``handle<index>``).
    """

    object: str
    min: Vec3
    max: Vec3
    keys: list | None = None
    usd: str | None = None
    prim: str | None = None
    joint: str | None = None
    name: str | None = None

    def validate(self, origin: str = "<scene>", index: int = 0, objects: tuple[str, ...] = ()) -> None:
        """Raise :class:`InputError` naming ``origin`` and ``handle[index]`` on the first bad value.

        ``objects``: the scene's body names, which ``object`` must be one of.
        """
        err = _Problem(origin, f"handle[{index}]: ")
        if not isinstance(self.object, str) or self.object not in objects:
            raise err("object", f"must name an object ({', '.join(objects)}), got {_shown(self.object)}")
        if self.name is not None:
            _check_name(err, self.name)
        _check_vec3(err, "min", self.min)
        _check_vec3(err, "max", self.max)
        if any(lo > hi for lo, hi in zip(self.min, self.max, strict=True)):
            raise err("min", f"must be <= max componentwise, got {list(self.min)} > {list(self.max)}")
        if (self.keys is None) == (self.usd is None):
            raise err("keys", "or usd (with prim or joint) is required, and only one of them")
        if self.keys is not None:
            for key in ("prim", "joint"):
                if getattr(self, key) is not None:
                    raise err(key, "names what of usd the handle follows; this handle has keys")
            _check_keys(err, "keys", self.keys)
            return
        if not isinstance(self.usd, str) or Path(self.usd).suffix.lower() not in USD_SUFFIXES:
            raise err("usd", f"must be a .usd, .usda or .usdc file, got {_shown(self.usd)}")
        if not Path(self.usd).is_file():
            raise err("usd", f"file not found: {self.usd}")
        if (self.prim is None) == (self.joint is None):
            raise err("prim", "(the animated prim) or joint is required with usd, and only one of them")
        if self.joint is not None:
            if not isinstance(self.joint, str) or not self.joint.startswith("/") or ":" not in self.joint:
                raise err("joint", f'must be "/Path/To/Skeleton:joint/path", got {_shown(self.joint)}')
        elif not isinstance(self.prim, str) or not self.prim.startswith("/"):
            raise err("prim", f'must be the animated prim\'s path, such as "/World/Hand", got {_shown(self.prim)}')


@dataclass
class CameraConfig:
    """Where the preview camera looks from (``warpfem run --preview``); unset keys are chosen automatically.

    Attributes:
        position: Camera position (m), or unset to frame every body.
        target: The point it looks at (m), or unset for the centre of the framed bodies.
        fov: Vertical field of view (degrees, 0 < fov < 180).
    """

    position: Vec3 | None = None
    target: Vec3 | None = None
    fov: float = 35.0

    def validate(self, origin: str = "<scene>") -> None:
        """Raise :class:`InputError` naming ``origin`` (the scene file) on the first bad value."""
        err = _table(origin, "camera")
        for key in ("position", "target"):
            if getattr(self, key) is not None:
                _check_vec3(err, key, getattr(self, key))
        _check_range(err, "fov", self.fov, "degrees", gt=0.0, lt=180.0)
        if self.position is not None and self.position == self.target:
            raise err("target", "must differ from position")


TETS_ACROSS_MAX = 64.0
"""The most tets across a body's thickness an object (and ``warpfem prepare --tets-across``) may ask for."""

MAX_TETS_RANGE = (100, 1_000_000)
"""The tet budgets an object's ``max_tets`` (and ``warpfem prepare --max-tets``) may give."""


@dataclass
class ObjectConfig:
    """One deformable body: a dense surface mesh, how to place it, and its material.

    The mesh is placed by scaling it about its file's origin, then rotating it (degrees, about X,
    then Y, then Z: USD's ``rotateXYZ``), then translating it.

    Attributes:
        name: Unique name, also the USD prim name: letters, digits and underscores, not starting
            with a digit.
        mesh: ``"builtin:bunny"`` or the absolute path of a surface mesh file (a relative path in
            the scene file resolves against the scene file's folder): OBJ, PLY, STL, OFF or USD.
        prim: For a USD mesh file, the ``UsdGeom.Mesh`` prim to use (default: the file's only mesh).
        subdivide: Loop subdivision iterations applied to the dense mesh (0..4; each multiplies
            the triangle count by 4).
        scale: Uniform scale factor (> 0).
        rotate: XYZ Euler angles (degrees).
        translate: Translation (m).
        velocity: Initial velocity of the body (m/s).
        angular_velocity: Initial angular velocity about the body's centre of mass (rad/s, world axes).
        faces: Target triangle count of the QEM-simplified coarse surface (100..20000).
        maxh: Netgen's maximum element size, relative to the coarse surface's bounding box
            diagonal (0 < maxh <= 1).
        tets_across: Tets across the body's thin parts (>= 0; ``maxh`` the largest size, ``faces`` the fewest
            faces): :func:`warpfem.prep.sizing.size_from_thickness`. 0: ``faces`` and ``maxh`` alone.
        max_tets: The tet budget of sizing by thickness (100..1000000).
        young: Young's modulus (Pa, > 0).
        poisson: Poisson's ratio (0 <= nu < 0.5).
        density: Mass density (kg/m^3, > 0).
        damping_mass: Rayleigh mass-proportional damping alpha (1/s, >= 0).
        damping_stiffness: Rayleigh stiffness-proportional damping beta (s, >= 0).
        pin_min: Lower corner of the pin box (m, world coordinates), or None: tet mesh vertices
            inside the box ``[pin_min, pin_max]`` are fixed.
        pin_max: Upper corner of the pin box (m); given together with ``pin_min``.
    """

    name: str
    mesh: str
    prim: str | None = None
    subdivide: int = 0
    scale: float = 1.0
    rotate: Vec3 = (0.0, 0.0, 0.0)
    translate: Vec3 = (0.0, 0.0, 0.0)
    velocity: Vec3 = (0.0, 0.0, 0.0)
    angular_velocity: Vec3 = (0.0, 0.0, 0.0)
    faces: int = 1000
    maxh: float = 0.2
    tets_across: float = 0.0
    max_tets: int = 50000
    young: float = 1e5
    poisson: float = 0.3
    density: float = 1000.0
    damping_mass: float = 0.0
    damping_stiffness: float = 0.0
    pin_min: Vec3 | None = None
    pin_max: Vec3 | None = None
    self_collision: bool = False
    collision_spacing: float = 0.0

    @property
    def is_builtin(self) -> bool:
        """Whether ``mesh`` names a built-in mesh rather than a file."""
        return isinstance(self.mesh, str) and self.mesh.startswith("builtin:")

    def validate(self, origin: str = "<scene>", index: int = 0) -> None:
        """Raise :class:`InputError` naming ``origin`` and ``object[index]`` on the first bad value."""
        err = _object_table(origin, index, self.name)
        if not isinstance(self.name, str) or not _NAME_RE.fullmatch(self.name):
            raise err(
                "name",
                "must be a valid USD prim name (letters, digits, underscores, not starting with a "
                f"digit), got {_shown(self.name)}",
            )
        self._validate_mesh(err)
        _check_int(err, "subdivide", self.subdivide, 0, 4)
        _check_range(err, "scale", self.scale, gt=0.0)
        for key in ("rotate", "translate", "velocity", "angular_velocity"):
            _check_vec3(err, key, getattr(self, key))
        _check_int(err, "faces", self.faces, 100, 20000)
        _check_range(err, "maxh", self.maxh, gt=0.0, le=1.0)
        _check_range(err, "tets_across", self.tets_across, ge=0.0, le=TETS_ACROSS_MAX)
        _check_int(err, "max_tets", self.max_tets, *MAX_TETS_RANGE)
        _check_range(err, "young", self.young, "Pa", gt=0.0)
        _check_range(err, "poisson", self.poisson, ge=0.0, lt=0.5)
        _check_range(err, "density", self.density, "kg/m^3", gt=0.0)
        _check_range(err, "damping_mass", self.damping_mass, "1/s", ge=0.0)
        _check_range(err, "damping_stiffness", self.damping_stiffness, "s", ge=0.0)
        if not isinstance(self.self_collision, bool):
            raise err("self_collision", f"must be true or false, got {_shown(self.self_collision)}")
        _check_range(err, "collision_spacing", self.collision_spacing, "m", ge=0.0)
        if (self.pin_min is None) != (self.pin_max is None):
            given, missing = ("pin_min", "pin_max") if self.pin_max is None else ("pin_max", "pin_min")
            raise err(missing, f"must be given together with {given} (both or neither)")
        if self.pin_min is not None:
            _check_vec3(err, "pin_min", self.pin_min)
            _check_vec3(err, "pin_max", self.pin_max)
            if any(lo > hi for lo, hi in zip(self.pin_min, self.pin_max, strict=True)):
                raise err(
                    "pin_min",
                    f"must be <= pin_max componentwise, got {list(self.pin_min)} > {list(self.pin_max)}",
                )

    def _validate_mesh(self, err: _Problem) -> None:
        if not isinstance(self.mesh, str) or not self.mesh:
            raise err("mesh", f'must be a file path or "{BUILTIN_BUNNY}", got {_shown(self.mesh)}')
        if self.is_builtin:
            if self.mesh not in BUILTIN_MESHES:
                raise err("mesh", f'is an unknown built-in mesh "{self.mesh}" (known: {BUILTIN_BUNNY})')
        elif not Path(self.mesh).is_file():
            raise err("mesh", f"file not found: {self.mesh}")
        if self.prim is not None:
            if Path(self.mesh).suffix.lower() not in (".usd", ".usda", ".usdc"):
                raise err("prim", "names a prim of a USD mesh file; this object's mesh is not one")
            if not isinstance(self.prim, str) or not self.prim.startswith("/"):
                raise err("prim", f'must be a prim path such as "/World/Mesh", got {_shown(self.prim)}')


@dataclass
class Scene:
    """A whole scene: timing, gravity, solver, ground and the bodies.

    Attributes:
        path: The scene file this came from (as given to :func:`load_scene`), or ``base_dir / name`` for
            :meth:`Scene.from_dict`.
        frames: Output frames to simulate (>= 1); frame 0, the initial pose, is written as well.
        fps: Output frames per second (> 0).
        substeps: Simulation steps per output frame (>= 1).
        gravity: Gravitational acceleration (m/s^2).
        up_axis: ``"Y"`` or ``"Z"``: the ground's normal, also written to the USD stage.
        solver: Linear solver settings.
        ground: Ground plane settings.
        collision: Body-body collision settings.
        camera: Preview camera.
        objects: The bodies (at least one, unique names).
        obstacles: Spheres, boxes and meshes, still or keyed.
        handles: Regions of bodies that follow animations.
    """

    path: Path
    frames: int = 120
    fps: float = 60.0
    substeps: int = 4
    gravity: Vec3 = (0.0, -9.81, 0.0)
    up_axis: str = "Y"
    solver: SolverConfig = field(default_factory=SolverConfig)
    ground: GroundConfig = field(default_factory=GroundConfig)
    collision: CollisionConfig = field(default_factory=CollisionConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    objects: list[ObjectConfig] = field(default_factory=list)
    obstacles: list[ObstacleConfig] = field(default_factory=list)
    handles: list[HandleConfig] = field(default_factory=list)

    @property
    def dt(self) -> float:
        """The simulation time step (s): ``1 / (fps * substeps)``."""
        return 1.0 / (self.fps * self.substeps)

    def validate(self) -> None:
        """Raise :class:`InputError` naming the scene file on the first bad value, table by table."""
        origin = str(self.path)
        err = _table(origin, "scene")
        _check_int(err, "frames", self.frames, 1)
        _check_range(err, "fps", self.fps, "frames/s", gt=0.0)
        _check_int(err, "substeps", self.substeps, 1)
        _check_vec3(err, "gravity", self.gravity)
        _check_choice(err, "up_axis", self.up_axis, ("Y", "Z"))
        self.solver.validate(origin)
        self.ground.validate(origin)
        self.collision.validate(origin)
        self.camera.validate(origin)
        for index, obstacle in enumerate(self.obstacles):
            obstacle.validate(origin, index)
        if not self.objects:
            raise InputError(f"{origin}: object: at least one [[object]] table is required")
        seen: dict[str, int] = {}
        for index, obj in enumerate(self.objects):
            obj.validate(origin, index)
            if obj.name in seen:
                raise _object_table(origin, index, obj.name)("name", f"is already used by object[{seen[obj.name]}]")
            seen[obj.name] = index
        for index, handle in enumerate(self.handles):
            handle.validate(origin, index, tuple(seen))
        for table, entries in (("obstacle", self.obstacles), ("handle", self.handles)):
            names = [e.name for e in entries if e.name is not None]
            for name in names:
                if names.count(name) > 1:
                    index = next(i for i, e in enumerate(entries) if e.name == name and i > names.index(name))
                    raise InputError(f"{origin}: {table}[{index}]: name is already used: {name}")

    @classmethod
    def from_dict(cls, doc: dict[str, Any], base_dir: str | Path = ".", name: str = "scene") -> Scene:
        """A scene from a dictionary shaped like a scene file (tables as dicts, ``object`` a list of dicts).

        Validated exactly as :func:`load_scene` validates a file, with the same one-line messages.

        Args:
            doc: The scene, e.g. ``{"scene": {"frames": 30}, "object": [{"name": "bunny", ...}]}``.
            base_dir: The folder relative mesh paths resolve against.
            name: Names the scene in messages (as ``<base_dir>/<name>``) and is the default output file's stem.

        Raises:
            InputError: The first bad table or key.
        """
        if not isinstance(doc, dict):
            raise InputError(f"{name}: a scene must be a dict of tables, got {type(doc).__name__}")
        return _from_doc(copy.deepcopy(doc), Path(base_dir) / name)

    def with_frames(self, frames: int) -> Scene:
        """A validated copy of this scene with ``frames`` replaced."""
        copy = dataclasses.replace(self, frames=frames)
        copy.validate()
        return copy


# ----------------------------------------------------------------------------------------------
# Reading TOML into the dataclasses


def _coerce(value: Any, default: Any) -> Any:
    """Give a TOML value the shape of its field, leaving anything else for ``validate`` to report.

    Ints for float fields become floats; lists of 3 numbers become tuples of floats.
    """
    if isinstance(default, float) and _is_number(value):
        return float(value)
    if (default is None or isinstance(default, tuple)) and isinstance(value, list):
        if len(value) == 3 and all(_is_number(v) for v in value):
            return tuple(float(v) for v in value)
    return value


def _build(cls: type, raw: dict[str, Any], err: _Problem, extra: dict[str, Any] | None = None) -> Any:
    """Make ``cls`` from a TOML table, rejecting unknown keys and applying defaults.

    ``extra`` holds the fields that do not come from this table (they are not valid keys in it).
    """
    kwargs: dict[str, Any] = dict(extra or {})
    fields = {f.name: f for f in dataclasses.fields(cls) if f.name not in kwargs}
    for key, value in raw.items():
        if key not in fields:
            close = difflib.get_close_matches(key, fields, n=1)
            hint = f" (did you mean {close[0]}?)" if close else ""
            raise err(key, f"is not a known key{hint}; known keys: {', '.join(fields)}")
        f = fields[key]
        default = f.default if f.default is not dataclasses.MISSING else None
        kwargs[key] = _coerce(value, default)
    for key, f in fields.items():
        if key not in kwargs and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise err(key, "is required")
    return cls(**kwargs)


def _sub_table(doc: dict[str, Any], origin: str, name: str) -> dict[str, Any]:
    value = doc.get(name, {})
    if not isinstance(value, dict):
        raise InputError(f"{origin}: {name} must be a table [{name}], got {_shown(value)}")
    return value


def _resolve_mesh(value: Any, folder: Path) -> Any:
    if not isinstance(value, str) or not value or value.startswith("builtin:"):
        return value
    return str((folder / value).resolve())


def load_scene(path: str | Path) -> Scene:
    """Read and validate a scene file.

    Args:
        path: The TOML scene file. Relative mesh paths in it resolve against its folder.

    Returns:
        The validated scene, every default applied.

    Raises:
        InputError: One line naming the file, the key and the problem (also for an unreadable file
            or a TOML syntax error).
    """
    path = Path(path)
    origin = str(path)
    try:
        with path.open("rb") as stream:
            doc = tomllib.load(stream)
    except OSError as exc:
        raise InputError(f"{origin}: cannot read the scene file: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        raise InputError(f"{origin}: the scene file is not UTF-8 text: {exc.reason}") from exc
    except tomllib.TOMLDecodeError as exc:
        message = str(exc).replace("\n", " ")
        raise InputError(f"{origin}: TOML syntax error: {message}") from exc
    return _from_doc(doc, path)


def _from_doc(doc: dict[str, Any], path: Path) -> Scene:
    """Build and validate a scene from a parsed document; ``path`` names it in messages and anchors meshes."""
    origin = str(path)
    known = ("scene", "solver", "ground", "collision", "camera", "object", "obstacle", "handle")
    _apply_preset(doc, origin)
    apply_mode_default(doc)
    for key in doc:
        if key not in known:
            close = difflib.get_close_matches(key, known, n=1)
            hint = f" (did you mean {close[0]}?)" if close else ""
            raise InputError(f"{origin}: {key} is not a known table{hint}; known tables: {', '.join(known)}")
    scene = _build(
        Scene,
        _sub_table(doc, origin, "scene"),
        _table(origin, "scene"),
        extra={
            "path": path,
            "solver": _build(SolverConfig, _sub_table(doc, origin, "solver"), _table(origin, "solver")),
            "ground": _build(GroundConfig, _sub_table(doc, origin, "ground"), _table(origin, "ground")),
            "collision": _build(CollisionConfig, _sub_table(doc, origin, "collision"), _table(origin, "collision")),
            "camera": _build(CameraConfig, _sub_table(doc, origin, "camera"), _table(origin, "camera")),
            "objects": _objects(doc, origin, path.parent),
            "obstacles": _array_of(doc, origin, "obstacle", ObstacleConfig, path.parent, ("mesh",)),
            "handles": _array_of(doc, origin, "handle", HandleConfig, path.parent, ("usd",)),
        },
    )
    scene.validate()
    return scene


def _objects(doc: dict[str, Any], origin: str, folder: Path) -> list[ObjectConfig]:
    raw_objects = doc.get("object", [])
    if not isinstance(raw_objects, list) or not all(isinstance(o, dict) for o in raw_objects):
        raise InputError(f"{origin}: object must be an array of tables, written [[object]]")
    objects = []
    for index, raw in enumerate(raw_objects):
        err = _object_table(origin, index, raw.get("name"))
        raw = dict(raw)
        if "mesh" in raw:
            raw["mesh"] = _resolve_mesh(raw["mesh"], folder)
        objects.append(_build(ObjectConfig, raw, err))
    return objects


def _array_of(
    doc: dict[str, Any], origin: str, table: str, cls: type, folder: Path, paths: tuple[str, ...]
) -> list[Any]:
    """The entries of an array of tables (``[[obstacle]]``, ``[[handle]]``), file keys resolved against ``folder``."""
    raw_entries = doc.get(table, [])
    if not isinstance(raw_entries, list) or not all(isinstance(o, dict) for o in raw_entries):
        raise InputError(f"{origin}: {table} must be an array of tables, written [[{table}]]")
    entries = []
    for index, raw in enumerate(raw_entries):
        raw = dict(raw)
        for key in paths:
            if key in raw:
                raw[key] = _resolve_mesh(raw[key], folder)
        entries.append(_build(cls, raw, _Problem(origin, f"{table}[{index}]: ")))
    return entries


def default_scene_path() -> Path:
    """The shipped default scene (a bunny dropped onto the ground), ``warpfem.scenes/default.toml``."""
    return Path(str(importlib.resources.files("warpfem.scenes") / "default.toml"))

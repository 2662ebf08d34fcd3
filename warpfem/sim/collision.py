"""Host side of collisions: the per-step detection and response of the collision points.

Detection: every step each body's tree of tet boxes (built by preprocessing) is refitted, and each collision
point walks the trees of the bodies whose boxes hold it (each box tested directly in scenes of up to
``DIRECT_BODIES`` bodies, else a ``wp.Bvh`` over the body boxes), then applies the barycentric inside test:
the paper's vertex-in-tet test (Teschner et al. 2003) with bounding volumes in place of the spatial hash.
One tree per body spares a point the walk through its own body's tets, which it always lies among.
Response (Kondo & Kanai, step 7): an implicit penalty force from the tet's distance field (see
:mod:`warpfem.kernels.collision`). Self-collision: a point is tested against its own body's tets only if
none of its anchor vertices (the vertex itself, or the corners of the surface triangle a sample lies on)
is a corner of the tet or shares a tet with one (the one-ring), so a body at rest has no false contacts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from warpfem.kernels import collision as K
from warpfem.kernels import contacts as KC
from warpfem.presets import CONTACT_DAMPING, CONTACT_OFFSET, CONTACT_OFFSET_LIMIT
from warpfem.sim.contacts import Coupling
from warpfem.sim.launch import CARRY_BODIES, DIRECT_BODIES, WARP_THREADS, WIDE_BLOCK, resident_blocks
from warpfem.sim.model import Model
from warpfem.sim.surface import visible_surface


@dataclass(frozen=True)
class CollisionSettings:
    """Collision response and capacity.

    Attributes:
        stiffness: Penalty stiffness per unit point mass (1/s^2): a = stiffness * m_point, where m_point is
            the lumped vertex mass interpolated at the point (a vertex: its own mass), so a point in contact
            behaves like the ground's penalty (resting depth about g / stiffness).
        friction: Coulomb friction coefficient between bodies, on a contact's depth up to the offset plus
            :data:`FRICTION_LOAD_DEPTH` of the size; none where bodies were placed deeper than that inside
            one another, until that overlap is undone (:meth:`Collider.mark_placed`).
        offset: How far outside another body's dense surface a contact with it starts, as a share of the
            scene's smallest colliding body's size: the penalty's give under a load is spent in that gap
            rather than inside the visible surface, and resting bodies stand up to that far apart.
        contacts_per_point: Contact buffer capacity per collision point.
        damping: Damping along the way out of a contact closing by more than the offset in a step, as a ratio
            to critical for its point's mass on its penalty spring (>= 0).
    """

    stiffness: float = 1.0e7
    friction: float = 0.5
    offset: float = CONTACT_OFFSET
    contacts_per_point: float = 2.0
    damping: float = CONTACT_DAMPING

    def __post_init__(self) -> None:
        if not self.stiffness > 0.0:
            raise ValueError(f"CollisionSettings.stiffness must be > 0 1/s^2, got {self.stiffness}")
        if not self.friction >= 0.0:
            raise ValueError(f"CollisionSettings.friction must be >= 0, got {self.friction}")
        if not (self.damping >= 0.0 and math.isfinite(self.damping)):
            raise ValueError(f"CollisionSettings.damping must be >= 0 and finite, got {self.damping}")
        if not 0.0 <= self.offset < CONTACT_OFFSET_LIMIT:
            raise ValueError(
                f"CollisionSettings.offset must be in [0, {CONTACT_OFFSET_LIMIT}) of the size, got {self.offset}"
            )
        if not self.contacts_per_point > 0.0:
            raise ValueError(f"CollisionSettings.contacts_per_point must be > 0, got {self.contacts_per_point}")


DEFAULT_COLLISION = CollisionSettings()

FRICTION_LOAD_DEPTH = 0.002
"""The deepest a body-body contact carries friction from, beyond the contact offset, as a share of the scene's
smallest colliding body's size: deeper, the penalty is undoing an overlap rather than carrying a load, and
friction in proportion to it holds overlapping bodies in place (they tangle instead of coming apart). Chosen
by measurement (docs/decisions.md, "Friction from the load, not the overlap")."""

LIFT_SHARE = 0.3
"""The share of the contact offset by which the collision points stand off their visible surface; the depth a
contact measures adds the rest, capped by the other body's cage margin over its visible surface, since
detection only sees points in its tets (``kernels.surface.contact_offset``). Lifted, a point reaches the
other body's tets, and its contact starts, at least this share of the offset outside that body's visible
surface even where the cage touches it; a point lifted by the whole offset passes through thin parts of the
other body sooner, whose nearest surface then lies behind it. Chosen by measurement (docs/decisions.md,
"Collision points lifted off the visible surface")."""

LATE_SOLVE_SHARE = 0.5
"""A late contact asks for a second solve only where the step's answer ends it deeper than this share of the
contact offset (counted from where the offset starts): a shallower one has not reached the visible surface, or
is within half the offset of it where the cage caps the part of the offset past the lift
(``kernels.surface.contact_offset``), and the next step answers it from its start. A pile at rest finds a few
such grazing contacts in most steps, and each would otherwise re-solve the whole scene."""

DETECT_LANES = 4
"""The most threads per collision point of contact detection on CUDA, each walking every ``lanes``-th of the
bodies whose boxes hold the point (:func:`detect_lanes`)."""

DETECT_FILL = 1024
"""Threads per SM that contact detection aims at: where the collision points are fewer than this times the
SMs, lanes share each point's bodies so that the launch fills the device; where they are more, a point has one
thread, since lanes then only add threads waiting on loads. Chosen by measurement on an H200
(docs/decisions.md)."""


def detect_lanes(points: int, device) -> int:
    """Threads per collision point of contact detection for ``points`` points on ``device`` (1 on the CPU).

    Any count finds the same contacts.
    """
    if not device.is_cuda:
        return 1
    return max(1, min(DETECT_LANES, device.sm_count * DETECT_FILL // max(points, 1)))


BODY_BLOCK = 256
"""Threads per body of the tree refit (CUDA)."""

DETECT_BLOCK = WARP_THREADS
"""Threads per block of contact detection (CUDA). The kernel's registers (and, through the body BVH, Warp's
query stack in shared memory, sized by the block) let an SM hold a single block of 256; blocks of one warp
let it hold more warps to hide the walks' loads (docs/decisions.md)."""


def lifted_weights(model: Model, lift: float) -> wp.array:
    """The collision points' weights with each point lifted off the visible surface by ``lift`` (m), at rest.

    Along the surface's outward normal there (``Model.point_normal``; points without one stay), in the cell
    that carries the point, beyond its faces if the lift leaves it: a point of one body then reaches another's
    tets, and its contact starts, ``lift`` outside that body's visible surface wherever the cage lies, which
    touches the visible surface in places. The model's own weights where nothing moves.
    """
    normal = model.point_normal.numpy().astype(np.float64)
    if lift == 0.0 or not normal.any():
        return model.point_bary
    corners = model.rest_x.numpy().astype(np.float64)[model.cells.numpy()[model.point_cell.numpy()]]
    edges = np.transpose(corners[:, 1:] - corners[:, :1], (0, 2, 1))  # columns x1 - x0, x2 - x0, x3 - x0
    w = np.linalg.solve(edges, lift * normal[:, :, None])[:, :, 0]  # the weights are affine in the position
    bary = model.point_bary.numpy().astype(np.float64) + np.concatenate([-w.sum(axis=1, keepdims=True), w], axis=1)
    return wp.array(bary.astype(np.float32), dtype=wp.vec4, device=model.device)


class Collider:
    """Buffers and launches of the collision stage for a model with collision points.

    Args:
        model: The model (its ``point_*`` arrays define the collision points).
        settings: Stiffness and capacity.
    """

    def __init__(self, model, settings: CollisionSettings) -> None:
        self.model = model
        n_points = model.point_cell.shape[0]
        self.capacity = max(64, int(settings.contacts_per_point * n_points))
        self._blocks = resident_blocks(model.device)
        """``max_blocks`` of the launches over the contact buffers' capacity, whose threads past the step's count
        leave at once (:func:`~warpfem.sim.launch.resident_blocks`)."""
        self._contact_buffers(n_points)
        self._tree_buffers(model)
        self._surface_terms(model, settings, n_points)
        self.set_response(settings.stiffness, settings.friction)

    def _contact_buffers(self, n_points: int) -> None:
        """The per-point and per-contact buffers detection fills and the response reads."""
        model, dev = self.model, self.model.device
        self.points = wp.zeros(n_points, dtype=wp.vec3, device=dev)
        self.point_velocity = wp.zeros(n_points, dtype=wp.vec3, device=dev)
        self.grad = wp.zeros(model.vertex_count, dtype=wp.vec3, device=dev)
        self.counts = wp.zeros(2, dtype=wp.int32, device=dev)
        """How many contacts the step found, and where those being answered start in the buffers (0, or a late
        pass's first): ``count`` and ``first``, views of it."""
        self.count, self.first = self.counts[0:1], self.counts[1:2]
        self._first = (wp.zeros(0, dtype=wp.int32, device=dev), self.first)  # what a prepare sets: nothing, first
        self._late_again = wp.zeros(1, dtype=wp.int32, device=dev)  # the count of a late pass answered twice
        self.contact_point = wp.zeros(self.capacity, dtype=wp.int32, device=dev)
        self.contact_cell = wp.zeros(self.capacity, dtype=wp.int32, device=dev)
        self.contact_bary = wp.zeros(self.capacity, dtype=wp.vec4, device=dev)
        self.contact_normal = wp.zeros(self.capacity, dtype=wp.vec3, device=dev)
        self.contact_depth = wp.zeros(self.capacity, dtype=float, device=dev)
        self.contact_matrix = wp.zeros(self.capacity, dtype=wp.mat33, device=dev)
        self.depth_max = wp.zeros(1, dtype=float, device=dev)
        self.found = K.Found()
        """The buffers above as detection's one output."""
        self.found.count, self.found.point, self.found.cell = self.count, self.contact_point, self.contact_cell
        self.found.bary, self.found.normal = self.contact_bary, self.contact_normal
        self.found.depth, self.found.deepest = self.contact_depth, self.depth_max
        self.coupling = Coupling(
            self.count,
            wp.zeros(self.capacity, dtype=wp.vec4i, device=dev),
            wp.zeros(self.capacity, dtype=wp.vec4, device=dev),
            wp.zeros(self.capacity, dtype=wp.vec4i, device=dev),
            wp.zeros(self.capacity, dtype=wp.vec4, device=dev),
            self.contact_matrix,
        )
        """The contacts as CG's matrix-free term (filled each step by :meth:`respond`)."""
        self.friction = wp.zeros(2, dtype=float, device=dev)
        """The friction coefficient and the deepest a contact carries friction from (m)."""
        self.point_stiffness = wp.zeros(n_points, dtype=float, device=dev)
        self.speed_max = wp.zeros(len(model.bodies), dtype=float, device=dev)
        self.contacts_total = wp.zeros(2, dtype=wp.int32, device=dev)  # sum over steps, max in a step
        self.point_contact = wp.zeros(n_points, dtype=wp.int32, device=dev)
        """Per point, the body of its one contact this step plus one, -1 if it touches more than one, 0 if none
        (``kernels.contacts.mark_contact``): what a late look leaves be (:meth:`respond_late`)."""
        self.placed = wp.zeros(n_points, dtype=wp.int32, device=dev)
        """Which points lay deeper than friction's load depth inside another body where the run began and have not
        come out of that depth since: their contacts carry no friction (:meth:`mark_placed`)."""
        self.placed_any = False
        """Whether :meth:`mark_placed` marked any point (else a step releases none)."""

    def _tree_buffers(self, model) -> None:
        """The tets' rest frames, the per-body tet trees' boxes and the bodies' boxes (and their BVH)."""
        dev = model.device
        self.tet_inverse = wp.zeros(model.tet_count, dtype=wp.mat33, device=dev)
        self.tet_origin = wp.zeros(model.tet_count, dtype=wp.vec3, device=dev)
        starts = np.array([b.tet_start for b in model.bodies] + [model.tet_count], dtype=np.int32)
        self.body_tet_start = wp.array(starts, dtype=wp.int32, device=dev)
        self.node_start = model.tree_node_start
        self.leaf_start = model.tree_leaf_start
        self.leaf_tets = model.tree_leaf_tets
        self.node_lower = wp.zeros(2 * model.tree_leaf_tets.shape[0] - len(model.bodies), dtype=wp.vec3, device=dev)
        self.node_upper = wp.zeros_like(self.node_lower)
        self.body_lowers = wp.zeros(len(model.bodies), dtype=wp.vec3, device=dev)
        self.body_uppers = wp.zeros(len(model.bodies), dtype=wp.vec3, device=dev)
        self.direct = len(model.bodies) <= DIRECT_BODIES
        """Whether detection tests every body's box itself rather than querying a BVH of them."""
        self.carries = not self.direct and len(model.bodies) > CARRY_BODIES
        """Whether a step may start from the step before's contacts (:meth:`respond`'s ``carried``): in scenes
        of many bodies, where the start's look at every point costs more than the carried contacts' walks (and
        detection goes through the body BVH, whose late look finds the pairs a carried start lacks)."""
        kept = self.capacity if self.carries else 0
        self.carried_count = wp.zeros(1, dtype=wp.int32, device=dev)
        self.carried_point = wp.zeros(kept, dtype=wp.int32, device=dev)
        self.carried_cell = wp.zeros(kept, dtype=wp.int32, device=dev)
        self.body_bvh = None
        if not self.direct:
            self._bound(model.rest_x)  # the body boxes the BVH is built from
            # median splits: a balanced tree (Warp's BVH queries keep a fixed 32-entry traversal stack)
            self.body_bvh = wp.Bvh(self.body_lowers, self.body_uppers, constructor="median")

    def _surface_terms(self, model, settings: CollisionSettings, n_points: int) -> None:
        """The visible surfaces, the lifted collision points and the depths set by the contact offset."""
        size = min(b.size for b in model.bodies)
        offset = settings.offset * size
        lift = LIFT_SHARE * offset
        self.visible, self._dense_meshes = visible_surface(model, offset - lift)
        """Each body's dense rest surface, for the exact depth of contacts near the surface."""
        self.point_bary = lifted_weights(model, lift)
        """The collision points' weights, lifted off the visible surface by a share of the offset
        (:data:`LIFT_SHARE`, :func:`lifted_weights`); the depth a contact measures adds the rest of it."""
        self._friction_depth = offset + FRICTION_LOAD_DEPTH * size
        """The deepest a contact carries friction from (m)."""
        self.solve_depth = LATE_SOLVE_SHARE * offset
        """How deep (m, counted from the offset's start) a late contact must end its step to ask for a second solve:
        see :data:`LATE_SOLVE_SHARE`."""
        self.lanes = detect_lanes(n_points, model.device)
        """Threads per collision point in contact detection (any count finds the same contacts)."""
        self.damping = float(settings.damping)
        """Damping of contacts closing fast, a ratio to critical (:class:`CollisionSettings`)."""
        self.closing_depth = offset
        """How far (m) a contact must close in a step to be damped: the offset, the room the penalty has before
        the visible surface."""

    def set_response(self, stiffness: float, friction: float) -> None:
        """Set the penalty stiffness per unit mass (1/s^2) and the friction coefficient (device arrays).

        The depth friction is read up to stays the scene's.
        """
        self.friction.assign(np.array([friction, self._friction_depth], dtype=np.float32))
        wp.launch(
            KC.scale_point_stiffness,
            dim=self.points.shape[0],
            inputs=[self.model.point_mass, float(stiffness)],
            outputs=[self.point_stiffness],
            device=self.model.device,
        )

    def prepare(self, x: wp.array, v: wp.array, late: bool = False) -> None:
        """What detection needs at positions ``x`` and velocities ``v`` that the elastic launch does not touch.

        The collision points and their velocities (the tet fields interpolated like the dense mesh), the tet
        inverses, the body trees and the body BVH. A step may run this alongside the elastic launch, on
        another stream (see ``Solver.phases``); :meth:`respond` needs it done first. ``late``: for a late pass,
        which also sets where its contacts start in the buffers (``first``).
        """
        m = self.model
        wp.launch(
            K.collision_points,
            dim=self.points.shape[0],
            inputs=[m.cells, x, v, m.point_cell, self.point_bary, m.point_body, self.count, self.capacity],
            outputs=[self.points, self.point_velocity, self.speed_max, self._first[late]],
            device=m.device,
        )
        self._bound(x)

    def respond(
        self,
        x: wp.array,
        v: wp.array,
        dt: float,
        force_out: wp.array,
        matrix_out: wp.array,
        cleared: bool = False,
        carried: bool = False,
    ) -> None:
        """Detect contacts at positions ``x`` and add their penalty forces and diagonal blocks to the outputs.

        Needs :meth:`prepare` at the same ``x`` and ``v`` first. Reads the rotated distance gradients in
        ``grad``: in a step the elastic launch sums them at ``x``; elsewhere call :meth:`rotate_gradients`
        first. ``cleared``: ``point_contact`` and ``counts`` are zero already (a step clears them with its
        own accumulators, in one launch). ``carried`` (where :attr:`carries`): only the (point, body) pairs of
        the contacts :meth:`keep` kept, each walked again at ``x``; a new pair waits for the step's late look,
        which looks for every pair the step has not found (:meth:`respond_late`).
        """
        if not cleared:
            self.point_contact.zero_()
            self.counts.zero_()
        if carried and self.carries:
            self._detect_carried(x, v, dt)
        else:
            self._detect(x, v, dt)
        self._answer(v, dt, force_out, matrix_out)

    def keep(self) -> None:
        """Keep the step's contacts (points and cells) for the next step's carried look (where :attr:`carries`)."""
        if self.carries:
            wp.launch(
                K.keep_contacts,
                dim=self.capacity,
                inputs=[self.count, self.contact_point, self.contact_cell],
                outputs=[self.carried_count, self.carried_point, self.carried_cell],
                device=self.model.device,
                max_blocks=self._blocks,
            )

    def contacts(self) -> tuple[np.ndarray, np.ndarray]:
        """The contacts in the buffers: (collision point, cell) of each, copied to the host.

        The last step's, or :meth:`contacts_at`'s (one host synchronisation).
        """
        count = min(int(self.count.numpy()[0]), self.capacity)
        return self.contact_point.numpy()[:count].copy(), self.contact_cell.numpy()[:count].copy()

    def contacts_at(self, x: wp.array, v: wp.array, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """The contacts a detection finds afresh at positions ``x``, as :meth:`contacts` gives them.

        For checks between frames: it rewrites the contact buffers, which the next step clears and fills again;
        the points' contact marks stay the last step's. Reads the rotated distance gradients the last step left
        in ``grad``.
        """
        self._detect_afresh(x, v, dt)
        return self.contacts()

    def _detect_afresh(self, x: wp.array, v: wp.array, dt: float) -> None:
        """Contacts at positions ``x`` into emptied buffers, outside a step (detection reads no contact marks)."""
        self.prepare(x, v)
        self.counts.zero_()
        self._detect(x, v, dt)

    def respond_late(
        self,
        x: wp.array,
        v: wp.array,
        dt: float,
        rhs_out: wp.array,
        matrix_out: wp.array,
        count_out: wp.array,
        base_out: tuple[wp.array, wp.array] | None = None,
    ) -> None:
        """Add the contacts that a solve's answer ``v`` (positions ``x``) makes and the step did not count.

        What the step's contacts so far mark is left be: in a scene that carries its contacts (:attr:`carries`),
        whose steps start from the step before's contacts alone, each (point, body) pair in contact and each
        point touching two bodies; elsewhere each point in contact. Each new contact enters the built system with the
        depth at the step's start its linearisation implies (see ``kernels.collision.store_contact``), its
        force times dt on ``rhs_out``; ``count_out[0]`` grows by how many of them ask for a second solve (those
        ending the step deeper than :attr:`solve_depth`). With ``base_out`` (the right-hand side and matrix
        without elasticity, which the rigid correction reads), there too.
        """
        self.prepare(x, v, late=True)
        self._detect(x, v, dt, late=True)
        self._answer(v, dt, rhs_out, matrix_out, count_out)
        if base_out is not None:
            self._answer(v, dt, *base_out, self._late_again)

    def mark_placed(self, x: wp.array, v: wp.array, dt: float) -> np.ndarray:
        """Mark the points lying deeper than friction's load depth inside another body at positions ``x``.

        Bodies placed inside one another are pressed apart by their penalties, which squeeze a body from
        opposite sides; friction from those contacts would hold it where it was put. A marked point's contacts
        carry no friction until one is no deeper than the load depth. For the state a run starts from (at its
        rest pose: no rotation), before the first step; its contacts are kept for the first step's carried look
        (:meth:`keep`), and none is left in the buffers. Returns the marks per collision point (bool, on the host).
        """
        m = self.model
        self.rotate_gradients(wp.full(m.tet_count, wp.mat33(np.eye(3, dtype=np.float32)), device=m.device))
        self._detect_afresh(x, v, dt)
        wp.launch(
            KC.mark_placed,
            dim=self.capacity,
            inputs=[self.count, self.contact_point, self.contact_depth, self.friction],
            outputs=[self.placed],
            device=m.device,
            max_blocks=self._blocks,
        )
        wp.copy(self.point_contact, self.placed)  # the first step's release keeps them
        self.keep()
        self.counts.zero_()
        self.depth_max.zero_()
        marked = self.placed.numpy() != 0
        self.placed_any = bool(marked.any())
        return marked

    def release_placed(self) -> None:
        """Clear the placed-inside mark of the points the last step found no contact for (before the step's clear).

        Nothing where no point was placed inside another body.
        """
        if self.placed_any:
            m = self.model
            n = self.placed.shape[0]
            wp.launch(KC.release_placed, dim=n, inputs=[self.point_contact], outputs=[self.placed], device=m.device)

    def _answer(
        self, v: wp.array, dt: float, force_out: wp.array, matrix_out: wp.array, late_count_out: wp.array | None = None
    ) -> None:
        """The penalty forces and blocks of the contacts from ``first`` on (late: onto the right-hand side)."""
        m = self.model
        dev = m.device
        wp.launch(
            KC.contact_forces,
            dim=self.capacity,
            inputs=[
                self.count,
                self.contact_point,
                self.contact_cell,
                self.contact_bary,
                self.contact_normal,
                self.contact_depth,
                v,
                m.cells,
                m.cell_body,
                m.point_cell,
                self.point_bary,
                self.point_stiffness,
                m.point_mass,
                self.damping,
                self.closing_depth,
                self.friction,
                m.diag_slot,
                dt,
                self.first,
                int(late_count_out is not None),
                self.solve_depth,
            ],
            outputs=[
                self.coupling.verts_a,
                self.coupling.weights_a,
                self.coupling.verts_b,
                self.coupling.weights_b,
                self.contact_matrix,
                force_out,
                matrix_out,
                self.contacts_total,
                self.point_contact,
                self.first if late_count_out is None else late_count_out,
                self.placed,
            ],
            device=dev,
            max_blocks=self._blocks,
        )

    def _bound(self, x: wp.array) -> None:
        """At positions ``x``: tet inverses and first corners, body trees and boxes, the body BVH (if any) refitted."""
        m = self.model
        threads = BODY_BLOCK if m.device.is_cuda else 1
        wp.launch_tiled(
            K.refit_trees,
            dim=[len(m.bodies)],
            inputs=[m.tets, x, self.body_tet_start, self.node_start, self.leaf_start, self.leaf_tets, threads],
            outputs=[
                self.tet_inverse,
                self.tet_origin,
                self.node_lower,
                self.node_upper,
                self.body_lowers,
                self.body_uppers,
            ],
            block_dim=threads,
            device=m.device,
        )
        if self.body_bvh is not None:
            self.body_bvh.refit()

    def rotate_gradients(self, rotation: wp.array) -> None:
        """grad = sum over incident tets of R_t g0, per tet vertex (detection normalises it where it reads it).

        The step gets this from the elastic launch; this is for callers outside a step.
        """
        m = self.model
        self.grad.zero_()
        wp.launch(
            K.accumulate_gradients,
            dim=m.tet_count,
            inputs=[m.tets, rotation, m.vertex_grad],
            outputs=[self.grad],
            device=m.device,
        )

    def _walk_inputs(self, x: wp.array, v: wp.array, dt: float) -> list:
        """The detection kernels' inputs for a walk through a body's tree, from its nodes to the points' anchors."""
        m = self.model
        return [
            self.node_start,
            self.leaf_start,
            self.leaf_tets,
            self.node_lower,
            self.node_upper,
            x,
            v,
            dt,
            m.tets,
            m.cells,
            self.tet_inverse,
            self.tet_origin,
            m.tet_slack,
            m.tet_face_start,
            m.tet_faces,
            m.tet_face_ids,
            m.face_depth,
            self.visible,
            self.points,
            self.point_velocity,
            m.point_body,
            m.point_anchor,
        ]

    def _depth_inputs(self) -> list:
        """The detection kernels' inputs for a contact's depth: the system's rows and the rotated distance field."""
        m = self.model
        return [m.row_start, m.cols, m.vertex_depth, self.grad]

    def _detect(self, x: wp.array, v: wp.array, dt: float, late: bool = False) -> None:
        """Contacts of the collision points, as :meth:`prepare` placed them, at positions ``x`` (``late``: appended)."""
        m = self.model
        lanes = self.lanes
        bodies = [self.body_lowers, self.body_uppers] if self.direct else [self.body_bvh.id]
        wp.launch(
            K.detect_contacts_direct if self.direct else K.detect_contacts,
            dim=self.points.shape[0] * lanes,
            inputs=[
                *bodies,
                *self._walk_inputs(x, v, dt),
                m.body_self,
                *self._depth_inputs(),
                lanes,
                self.point_contact,
                (K.LATE_BY_PAIR if self.carries else K.LATE_BY_POINT) if late else 0,
            ],
            outputs=[self.found],
            device=m.device,
            block_dim=DETECT_BLOCK if m.device.is_cuda else WIDE_BLOCK,
        )

    def _detect_carried(self, x: wp.array, v: wp.array, dt: float) -> None:
        """Contacts at positions ``x`` of the (point, body) pairs :meth:`keep` kept."""
        m = self.model
        wp.launch(
            K.detect_carried,
            dim=self.capacity,
            inputs=[
                self.carried_count,
                self.carried_point,
                self.carried_cell,
                m.cell_body,
                *self._walk_inputs(x, v, dt),
                *self._depth_inputs(),
            ],
            outputs=[self.found],
            device=m.device,
            block_dim=DETECT_BLOCK if m.device.is_cuda else WIDE_BLOCK,
            max_blocks=resident_blocks(m.device, DETECT_BLOCK),
        )

    def read_stats(self) -> tuple[int, int, float, bool]:
        """Contact statistics since the last call (one host synchronisation).

        Returns:
            (contacts summed over steps, most contacts in one step, deepest contact (m), buffer overflowed).
        """
        total, most = (int(c) for c in self.contacts_total.numpy())
        depth = float(self.depth_max.numpy()[0])
        self.contacts_total.zero_()
        self.depth_max.zero_()
        return total, most, depth, most > self.capacity

    def read_speeds(self) -> np.ndarray:
        """Per body, the fastest collision point's speed (m/s) since the last call (one host synchronisation)."""
        speeds = self.speed_max.numpy().copy()
        self.speed_max.zero_()
        return speeds

"""Collision handling for the stepper: proximity impulses, CCD, impulses at the time of impact.

:class:`ImpulseCollisionHandler` is plugged into :class:`sim.integrator.SemiImplicitIntegrator`
as its ``collision_handler``. Per substep of length ``h`` it receives the start State and the
predicted end State (velocities ``v-`` after forces) and works on one set of collidable vertices:
cloth particles, rigid-body surface vertices (body frame -> world) and static mesh vertices; the
model's components decide which groups exist and which may touch (cloth with itself only with
``"self_collision"``, a rigid body never with itself, static meshes never with each other).

1. **Proximity** (resting and sliding contact, after Bridson et al. 2002): vertex-face and
   edge-edge pairs closer than the separation ``delta`` at the start of the substep become
   contacts at ``t* = 0`` with the normal of their exact closest points. Their impulses keep the
   normal relative velocity at least ``-e v_n-`` (restitution ``e``) and at least
   ``SEPARATION_RATE (delta - d) / h``, so resting primitives neither approach nor get pushed
   apart faster than a tenth of the missing gap per substep.
2. **Continuous collision detection**: the planned motion (linear per vertex from the start to
   the planned end positions) goes through :class:`collision.broad_phase.BroadPhase` and the
   vertex-face / edge-edge narrow phase of :mod:`kernels.ccd` at zero thickness (the coplanarity
   cubic and its robust roots: the exact first contact time ``t*``). Every hit whose primitives
   still approach at ``t*`` joins the contact set, with the normal at ``t*`` oriented by the
   start offset and the target ``max(-e v_n-, SEPARATION_RATE delta / h)``.
3. **Impulses** for the whole contact set: projected Gauss-Seidel sweeps in a Warp kernel
   (:func:`kernels.contact.solve_contacts_kernel`, sequential, deterministic), accumulated normal
   impulses clamped to ``>= 0`` and Coulomb friction clamped to the cone ``|j_t| <= mu j_n``. Cloth impulses split by the barycentric / segment weights and the
   inverse masses; rigid ones change the linear and the angular velocity (world inverse inertia).
4. **Time-of-impact integration**: every particle or body whose velocity changed moves with its
   old velocity until its earliest contact ``t*`` and with the new one after,
   ``x(h) = x0 + t* v- + (h - t*) v+`` (bodies: the centre of mass the same way, the orientation
   turned by ``w-`` for ``t*`` and then by ``w+``).
5. 2-4 repeat until the planned motion is collision free or ``max_iterations`` rounds are done;
   then the fail-safe forms **rigid impact zones** (Provot 1997; Bridson et al. 2002): the
   particles and bodies joined by a still-approaching contact move as one rigid body over the
   whole substep with their total linear and angular momentum (at rest when the zone holds a
   static vertex or a pinned particle), and the zones grow until CCD finds no approaching
   contact. A zone's straight vertex paths are an invertible affine motion, so nothing inside it
   can collide, and the start of a substep is collision free: this terminates without
   interpenetration.

Two forms share the detection: the default one above (its decisions and its projected
Gauss-Seidel impulses in numpy and Warp kernels around the Warp broad and narrow phases, which
read the candidate pairs where the broad phase left them; it reuses its buffers, so stepping
allocates no Warp array, and its cost is measured per scene in ``benchmarks/sim.py``), and with
``differentiable=True`` the replayed one (design.md "Differentiating collision response:
decide, then replay"): decisions off the tape, then ``t*`` through the mollified roots, the
exact impulse solve, the time-of-impact integration and the impact zones' rigid motion as taped
Warp launches (:mod:`collision.replay`).
"""

from __future__ import annotations

import contextlib
import itertools

import numpy as np
import warp as wp

from collision.broad_phase import BroadPhase
from collision.buffers import RecordedLaunches, Staging, host, read_only, upload
from collision.ccd import ONES3, CandidateNarrowPhase
from kernels.variants import check_settings as check_ccd_settings
from collision.mesh import VERTEX_BODY as _BODY
from collision.mesh import VERTEX_PARTICLE as _PARTICLE
from collision.mesh import VERTEX_STATIC as _STATIC
from collision.mesh import CollisionMesh
from collision.replay import ContactReplay, active_tape, paused_tape
from collision.roots import DEFAULT_MAX_DERIVATIVE
from kernels.contact import (contact_geometry_kernel, pair_weights_kernel,
                             planned_substep_kernel, pose_substep_kernel, pose_vertices_kernel,
                             solve_contacts_kernel)
from sim.model import Model, State
from sim.rotation import cross, quat_to_matrix, row_norms

SEPARATION_RATE = 0.1
"""Fraction of the missing separation ``delta - d`` a proximity impulse restores per substep
(Bridson et al. 2002 use the same order); larger values make resting contacts jitter."""

DEFAULT_SEPARATION_RELATIVE = 1e-4
"""Separation used when the model's thickness is 0: this fraction of the diagonal of the
collidable vertices' bounding box at the start (1e-4 m for a 1 m scene)."""

SOLVER_ITERATIONS = 500
"""Most projected Gauss-Seidel sweeps per impulse solve (it stops earlier once every contact's normal
velocity is within :data:`SOLVER_TOLERANCE` of its target)."""

SOLVER_TOLERANCE = 0.05
"""Stop the Gauss-Seidel sweeps when no contact's normal velocity is below its target by more than this
fraction of the separation speed ``SEPARATION_RATE delta / h``."""

TOUCHING_RELATIVE = 1e-6
"""Proximity pairs closer than this fraction of the separation count as touching: their offset
direction is rounding noise, so the normal comes from the primitives' geometry instead."""

APPROACH_EPS = 1e-12
"""A CCD hit counts as approaching when its normal relative velocity is below ``-APPROACH_EPS``
times the contact's largest vertex speed plus the separation speed (float64 rounding of a
velocity that is exactly separating or tangential stays far inside)."""

END_OF_SUBSTEP = 1e-9
"""A CCD hit this close (relative) to the end of the substep lies on the end of the planned path;
its approach is judged by the velocities at ``t*`` alone (see ``_approach``)."""

PLANE_ROUNDING_SLACK = 1e-9
"""A particle counts as a plane's proximity contact below ``(1 - PLANE_ROUNDING_SLACK) delta``:
the integrator's plane stage leaves it at ``delta`` exactly, which the distance's rounding may
put a hair below (rigid vertices, which only the handler holds, keep the plain ``delta``)."""

COVER_MARGIN = 4.0
"""Margin of the substep's one broad-phase query, in separations ``delta``: the proximity pass
and every CCD round whose planned end positions stay within ``0.45 COVER_MARGIN delta`` of the
covered boxes (the predicted motion continued, :data:`COVER_AHEAD`) reuse its candidates
(:class:`collision.ccd.CandidateNarrowPhase`); a round that moves further queries afresh."""

COVER_SLACK = 1.0
"""A substep keeps an earlier substep's broad-phase query (instead of a new one) while its start
and predicted end positions lie within this many separations ``delta`` of the boxes of the
covered motion (per coordinate): slow and resting contact moves less than that per substep, so
one query serves several substeps. The
proximity pass still has ``0.45 (COVER_MARGIN - 1) delta - COVER_SLACK delta >= 0`` of room and
the CCD rounds ``0.45 COVER_MARGIN delta - COVER_SLACK delta``; a call beyond its room queries
afresh, so the contacts are the same as with a query per substep."""

CCD_REACH_SLACK = 0.5
"""How much farther than predicted [separations] a vertex may end from its start before the
CCD rounds test every candidate instead of those that the proximity pass kept for them
(:meth:`ImpulseCollisionHandler._proximity_rows`). Resting contact's rounds change the
predicted motion by about ``SEPARATION_RATE`` separations; measured over 100 steps, 0.5 kept
the short list in 96% of cloth_drop's CCD rounds (154 pairs instead of ~2000), 0.25 in 89%
(55 pairs), 1.0 in 98% (343 pairs)."""

CCD_REACH_MIN_CANDIDATES = 64
"""Fewest candidate pairs of the cover for which the proximity pass keeps the CCD rounds'
pairs: below it, testing them all costs about what keeping them does (rigid_toss has ~30-50).
A wide cover (:data:`COVER_SCALES`) holds a few hundred: cloth_rigid's CCD rounds then test 63
pairs per substep instead of 233."""

COVER_AHEAD = 5.0
"""The substep's broad-phase query covers each vertex's predicted motion continued for this
many more substeps (at most :data:`COVER_AHEAD_LIMIT` separations per coordinate), so that
steady motion stays inside its covered box, and the cover is kept (:data:`COVER_SLACK`), for
several substeps. The hits are the same (the calls check their own motion against the covered
one); the pairs the query finds grow only along the motion. Measured on the benchmark scenes
(300 steps): broad-phase queries 2479 -> 872 (cloth_rigid, whose cloth swings about 4
separations per substep), 1117 -> 386 (cloth_drop), 346 -> 83 (rigid_toss)."""

COVER_AHEAD_LIMIT = 32.0
"""Longest continuation [separations] of a vertex's motion in the broad-phase query (fast
vertices leave their cover anyway; this keeps their boxes, and the candidate pairs, small)."""

COVER_SCALES = (1.0, 2.0, 4.0, 8.0)
"""Factors on :data:`COVER_MARGIN`, :data:`COVER_SLACK` and :data:`COVER_AHEAD_LIMIT`: a scene
whose broad-phase queries find few candidate pairs (a cloth swinging free, a ball rolling on a
floor) widens its cover a step after each query that finds fewer than
:data:`COVER_SPARSE_CANDIDATES`, and narrows it a step after each that finds more than
:data:`COVER_DENSE_CANDIDATES` (a draped cloth). A wide cover is kept for more substeps of
fast or turning motion, at the price of more candidates to test per call; the hits are the same
whatever the cover. Measured on cloth_rigid (hanging cloth and rolling ball), steps 20-100:
0.46 queries per substep at factor 1 (29 candidates each), 0.18 at factor 8 (186)."""

COVER_SPARSE_CANDIDATES = 128
"""See :data:`COVER_SCALES`."""

COVER_DENSE_CANDIDATES = 1024
"""See :data:`COVER_SCALES`."""

ACTIVE_SET_ITERATIONS = 20
"""Most repairs of the active set (drop pulling contacts, add violated ones, switch between
sticking and sliding) after the exact solve of the replayed response."""

class _Contacts:
    """The contact set of one substep (grows over the CCD rounds; keyed by primitive pair).

    Args:
        key_base: more than any index a pair holds (vertex, face, edge or plane): a pair
            ``(kind, a, b)`` is keyed by the one integer ``(kind key_base + a) key_base + b``.
    """

    # the empty set's rows: shared read-only arrays (every substep makes a set; its first add()
    # replaces them all, so later ones only concatenate to or write into the set's own rows)
    key, idx, kind = read_only(np.zeros(0, dtype=np.int64), np.zeros((0, 4), dtype=np.int64), np.zeros(0, dtype=np.int64))
    w, n = read_only(np.zeros((0, 4)), np.zeros((0, 3)))
    toi, target, jn, jt = read_only(np.zeros(0), np.zeros(0), np.zeros(0), np.zeros((0, 3)))
    edge_edge, timed = read_only(np.zeros(0, dtype=bool), np.zeros(0, dtype=bool))

    def __init__(self, key_base: int) -> None:
        # rows (see the class attributes' empties): key: the pair of each row as one integer
        # (see _keys); idx (C, 4) vertex indices (CCD order); kind: 0 vertex-face, 1 edge-edge,
        # 2 vertex-plane; w (C, 4) weights: side A positive (sum 1), side B negative (sum -1);
        # n (C, 3): unit normal from side B to side A; toi: time of impact in the substep [s];
        # target: minimum normal relative velocity after the impulse [m/s]; timed: the time comes
        # from a root or a plane crossing, so the replay differentiates it (not a constant:
        # proximity, collinear or advancement detections); jn, jt (C, 3): accumulated normal /
        # friction impulses [N s]
        self.key_base = int(key_base)

    def __len__(self) -> int:
        return len(self.toi)

    def _keys(self, kind: np.ndarray, pair: np.ndarray) -> np.ndarray:
        pair = np.asarray(pair, dtype=np.int64).reshape(-1, 2)
        return (np.asarray(kind, dtype=np.int64) * self.key_base + pair[:, 0]) * self.key_base + pair[:, 1]

    def _rows(self, keys: np.ndarray) -> np.ndarray:
        """(C,) the row of each key in the set, -1 where the pair is not in it (keys are unique
        per row, so a sorted search finds at most one)."""
        if not len(self.key):
            return np.full(len(keys), -1, dtype=np.int64)
        order = np.argsort(self.key)
        ordered = self.key[order]
        at = np.minimum(np.searchsorted(ordered, keys), len(ordered) - 1)
        return np.where(ordered[at] == keys, order[at], -1)

    def _first(self, keys, kind, idx, w, n, toi, target, timed, copy):
        """:meth:`add` into the empty set (every substep's first: no pair is in the set yet)."""
        c = len(keys)
        array = np.array if copy else np.asarray
        kind = array(kind, dtype=np.int64)
        self.key, self.kind, self.edge_edge = keys, kind, kind == 1
        self.idx, self.w, self.n = array(idx, dtype=np.int64), array(w, dtype=np.float64), array(n, dtype=np.float64)
        self.toi, self.target = array(toi, dtype=np.float64), array(target, dtype=np.float64)
        self.timed = np.zeros(c, dtype=bool) if timed is None else np.array(timed, dtype=bool)
        self.jn, self.jt = np.zeros(c), np.zeros((c, 3))
        zero = np.zeros(c, dtype=np.int64)
        return np.arange(c), zero, zero.copy()

    def at_end(self, kind: np.ndarray, pair: np.ndarray, toi: np.ndarray, h: float) -> np.ndarray:
        """(C,) bool: the pair is in the set already, at the very end of the substep ``h`` [s],
        and detected there again (``toi`` [s])."""
        end = h * (1.0 - END_OF_SUBSTEP)
        row = self._rows(self._keys(kind, pair))
        found = row >= 0
        if not found.any():
            return found
        return found & (self.toi[np.maximum(row, 0)] >= end) & (np.asarray(toi) >= end)

    def add(self, kind: np.ndarray, pair: np.ndarray, idx, w, n, toi, target, timed=None, copy=True,
            distinct=False):
        """Adds contacts, pairs distinct (a pair already present takes the new normal, weights
        and target, and the earlier of the two times). ``timed`` (C,) bool: the time is
        differentiated by the replay (default: none is). ``copy=False``: the set may keep the
        arrays given (the caller's own, not used after). ``distinct=True``: the caller's rows
        are distinct pairs by construction (the proximity pass: each candidate pair once, each
        vertex-plane pair once), so the check for a repeated pair is skipped.

        Returns:
            (new_index, keep_old_toi, keep_old_target) over the grown set: the row of the
            arguments each contact now takes its geometry from (-1: unchanged), and whether it
            kept its old time / target (the decisions the taped replay repeats).
        """
        keys = self._keys(kind, pair)
        if not distinct and len(keys) > 1 and not np.diff(np.sort(keys)).all():  # a repeated key (np.unique, cheaper)
            raise ValueError("pair: a contact pair appears twice in one call (the rows must be distinct pairs)")
        before = len(self.toi)
        if before == 0:
            return self._first(keys, kind, idx, w, n, toi, target, timed, copy)
        new_index = np.full(before, -1, dtype=np.int64)
        keep_toi = np.zeros(before, dtype=np.int64)
        keep_target = np.zeros(before, dtype=np.int64)
        timed = np.zeros(len(pair), dtype=bool) if timed is None else np.asarray(timed, dtype=bool)
        row = self._rows(keys)
        old = np.flatnonzero(row >= 0)  # arguments whose pair is in the set already
        if len(old):
            at = row[old]
            self.w[at], self.n[at] = w[old], n[old]
            new_index[at] = old
            kept_toi = self.toi[at] <= toi[old]
            kept_target = self.target[at] >= target[old]
            keep_toi[at] = kept_toi
            keep_target[at] = kept_target
            self.timed[at] = np.where(kept_toi, self.timed[at], timed[old])
            # the earlier time and the larger target, ties (and NaN) keeping the old value (as
            # Python's min / max did)
            self.toi[at] = np.where(toi[old] < self.toi[at], toi[old], self.toi[at])
            self.target[at] = np.where(target[old] > self.target[at], target[old], self.target[at])
        r = np.flatnonzero(row < 0)  # new pairs
        if len(r):
            rows = {"key": keys[r], "idx": idx[r], "kind": kind[r], "w": w[r], "n": n[r], "toi": toi[r],
                    "target": target[r], "edge_edge": kind[r] == 1, "timed": timed[r], "jn": np.zeros(len(r)),
                    "jt": np.zeros((len(r), 3))}
            for name, value in rows.items():
                # the first contacts of a substep need no concatenation (the rows are copies)
                setattr(self, name, np.concatenate([getattr(self, name), value]) if before else value)
            new_index = np.concatenate([new_index, r])
            keep_toi = np.concatenate([keep_toi, np.zeros(len(r), dtype=np.int64)])
            keep_target = np.concatenate([keep_target, np.zeros(len(r), dtype=np.int64)])
        return new_index, keep_toi, keep_target


class _CallContacts:
    """The contacts of one handler call, for its ``last_*`` statistics, worked out when first
    read: the recorder, the implicit integrator and the benchmarks read them, a plain stepping
    loop does not (working them out on every call cost about 0.1 ms per substep).

    Args:
        cs: the call's contact set (not changed after the call), or None (no contact).
        x0, x1: the vertices' positions (V + 1, 3) at the start and the planned end [m]
            (copied here when a contact received an impulse: they may be reused buffers).
        h: the substep [s].
        vertex_type: (V + 1,) the vertex kinds.
    """

    def __init__(self, cs=None, x0=None, x1=None, h=1.0, vertex_type=None) -> None:
        self._active = (cs.jn > 0) if cs is not None and len(cs) else np.zeros(0, dtype=bool)
        self.count = int(np.count_nonzero(self._active))
        if self.count:
            x0, x1 = x0.copy(), x1.copy()
        self._args = (cs, x0, x1, h, vertex_type)
        self._contacts = None
        self._body_particles = None

    def contacts(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(points (C, 3) [m]: side A's closest point at ``t*`` on the straight paths x0 -> x1,
        normals (C, 3), times of impact (C,) [s]) of the contacts that received an impulse."""
        if self._contacts is None:
            cs, x0, x1, h, _ = self._args
            active = self._active
            if active.any():
                ia = cs.idx[active]
                side_a = np.abs(np.where(np.arange(4) < np.where(cs.edge_edge[active], 2, 1)[:, None],
                                         cs.w[active], 0.0))
                y = x0[ia] + (cs.toi[active] / h)[:, None, None] * (x1[ia] - x0[ia])
                self._contacts = (np.einsum("ck,ckd->cd", side_a, y), cs.n[active], cs.toi[active])
            else:
                self._contacts = (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
        return self._contacts

    def body_particles(self) -> np.ndarray:
        """(K,) int64 the particles (sorted, distinct) that share a contact with a rigid body's
        vertex."""
        if self._body_particles is None:
            cs, vertex_type = self._args[0], self._args[4]
            self._body_particles = np.zeros(0, dtype=np.int64)
            if cs is not None and len(cs):
                types = vertex_type[cs.idx]
                rows = (types == _BODY).any(axis=1)
                if rows.any():
                    self._body_particles = np.unique(cs.idx[rows][types[rows] == _PARTICLE])
        return self._body_particles


_NO_CONTACTS = _CallContacts()
"""The record of a call without contacts (shared: a record is not changed after it is made)."""

# no CCD hit (ImpulseCollisionHandler._ccd_candidates): kind, pair, vertex indices, time, source
_NO_HITS = read_only(np.zeros(0, dtype=np.int64), np.zeros((0, 2), dtype=np.int64), np.zeros((0, 4), dtype=np.int64),
                     np.zeros(0), np.zeros(0, dtype=np.int64))


# no vertex near a plane (ImpulseCollisionHandler._plane_proximity): kind, pair, vertex indices,
# distance; and an empty index array
_NO_PLANE_ROWS = read_only(np.zeros(0, dtype=np.int64), np.zeros((0, 2), dtype=np.int64),
                           np.zeros((0, 4), dtype=np.int64), np.zeros(0))
_NONE_INDEX = _NO_PLANE_ROWS[0]

CCD_OPTIONS = ("precision", "tolerance_scale", "max_iterations", "tolerance")
"""Keys of ``ImpulseCollisionHandler(ccd_options=...)``: the narrow phase's knobs."""


def check_ccd_options(ccd_options) -> dict:
    """``ccd_options`` validated (a dict with keys of :data:`CCD_OPTIONS`, values as
    :func:`kernels.variants.check_settings` takes them; None: {}), as a new dict.

    Raises:
        ValueError: naming ``ccd_options`` or the bad key.
    """
    if ccd_options is None:
        return {}
    if not isinstance(ccd_options, dict):
        raise ValueError(f"ccd_options must be a dict or None, got {type(ccd_options).__name__}")
    unknown = set(ccd_options) - set(CCD_OPTIONS)
    if unknown:
        raise ValueError(f"ccd_options: unknown keys {sorted(map(repr, unknown))}; expected some of {CCD_OPTIONS}")
    try:
        check_ccd_settings(**ccd_options)
    except ValueError as exc:
        raise ValueError(f"ccd_options: {exc}") from None
    return dict(ccd_options)


def contact_separation(model: Model, mesh: CollisionMesh | None = None) -> float:
    """The separation ``delta`` [m] every contact keeps (:attr:`ImpulseCollisionHandler.separation`;
    the integrator's particle-plane stage keeps it too while a handler runs): the model's
    thickness, or when that is 0, :data:`DEFAULT_SEPARATION_RELATIVE` of the diagonal of the
    collidable vertices' bounding box at the model's start (1e-6 m without vertices)."""
    if float(model.thickness) > 0.0:
        return float(model.thickness)
    mesh = CollisionMesh.from_model(model) if mesh is None else mesh
    if not mesh.vertex_count:
        return 1e-6
    x = mesh.positions(model.particle_q.numpy()[: mesh.particle_count] if mesh.particle_count else np.zeros((0, 3)),
                       model.body_q.numpy() if model.body_count else np.zeros((0, 7)))
    diag = float(np.linalg.norm(x.max(0) - x.min(0)))
    return DEFAULT_SEPARATION_RELATIVE * diag if diag > 0 else 1e-6


class ImpulseCollisionHandler:
    """Proximity + CCD + impulse response at the time of impact (see the module docstring).

    Args:
        model: the finalised model (its surfaces, masses, restitution, friction, thickness).
        max_iterations: CCD/response rounds before the fail-safe.
        differentiable: the decide-then-replay response (:meth:`_call_replayed`), which a
            ``wp.Tape`` can record, instead of Gauss-Seidel impulses.
        max_derivative: the robust-division bound ``M`` of the replayed times of impact.
        ccd_options: the narrow phase's knobs that decide the CCD contacts, a dict of
            ``precision`` ("float64" / "float32"), ``tolerance_scale``, ``max_iterations`` and
            ``tolerance`` (:class:`collision.ccd.CandidateNarrowPhase`); None: the float64
            kernels as written. The replay recomputes each contact's ``t*`` with the float64
            root solver (and its mollified derivative) either way.

    Attributes (of the last call, for logging and tests):
        last_contacts: (C, 3) contact points [m] (side A's closest point at ``t*``) of the
            contacts that received an impulse.
        last_normals: (C, 3) their unit normals.
        last_times: (C,) their times of impact from the start of the substep [s].
        last_contact_count: C (cheap: the three above are worked out when first read).
        last_body_particles: the particles that touched a rigid body's vertex in the last call.
        failsafe_count: substeps (over the handler's life) in which the fail-safe froze something.
        untaped_substeps: substeps (``differentiable=True``) whose response carries no
            derivative; always 0 since the impact zones' motion is taped (kept for
            compatibility).
        active_set_repairs: exact solves redone because the active set changed.
        unsettled_active_sets: solves whose active set still changed after
            :data:`ACTIVE_SET_ITERATIONS` repairs (the last trial's set is used).
        separation: the separation ``delta`` [m] the proximity pass keeps.
    """

    def __init__(self, model: Model, max_iterations: int = 8, differentiable: bool = False,
                 max_derivative: float = DEFAULT_MAX_DERIVATIVE, ccd_options: dict | None = None):
        self.model = model
        self.ccd_options = check_ccd_options(ccd_options)
        self.max_iterations = int(max_iterations)
        self.differentiable = bool(differentiable)
        self.max_derivative = float(max_derivative)
        m = model
        mesh = self.mesh = CollisionMesh.from_model(model)
        self.n_particles = mesh.particle_count
        self.shape_offset = mesh.shape_offset
        self.n_shape = mesh.shape_count
        self.static_offset = mesh.static_offset
        self.shape_vertices = mesh.shape_local
        self.shape_body = mesh.shape_body
        self.static_vertices = mesh.static_vertices
        self.n_vertices = mesh.vertex_count
        self.faces, self.edges = mesh.faces, mesh.edges
        # broad-phase groups: the particles (self-collision only with "self_collision"), each
        # body (never with itself), the static meshes (never with each other)
        groups, self_collision, static = [], [], []
        if self.n_particles:
            groups.append(np.zeros(self.n_particles, dtype=np.int64))
            self_collision.append("self_collision" in model.components)
            static.append(False)
        if self.n_shape:
            groups.append(len(self_collision) + self.shape_body)
            self_collision.extend([False] * m.body_count)
            static.extend([False] * m.body_count)
        if len(self.static_vertices):
            groups.append(np.full(len(self.static_vertices), len(self_collision), dtype=np.int64))
            self_collision.append(False)
            static.append(True)
        # one dummy static vertex (index n_vertices, at the origin): the second side of
        # vertex-plane contacts
        self.vertex_type = np.append(mesh.vertex_type, _STATIC).astype(np.int64)
        self.vertex_owner = np.append(mesh.vertex_owner, 0).astype(np.int64)
        self.planes = m.planes.numpy().reshape(-1, 4) if m.plane_count else np.zeros((0, 4))
        # the vertices the vertex-plane tests cover (movable particles and the rigid surface
        # vertices) and the planes' normals / offsets. The integrator's plane stage has already
        # stopped the particles at the planes when the handler runs, but a mesh contact's
        # impulse can push a particle back through (cloth pressed into the ground by a body):
        # as rows of the same solve the plane holds it
        particle_inv_mass = m.particle_inv_mass.numpy() if mesh.particle_count else np.zeros(0)
        movable_particles = np.flatnonzero(particle_inv_mass > 0)
        self._plane_vertex_ids = np.concatenate([movable_particles, np.arange(mesh.shape_offset, mesh.static_offset)])
        self._plane_threshold = np.concatenate([np.full((len(movable_particles), 1), 1.0 - PLANE_ROUNDING_SLACK),
                                                np.ones((self.n_shape, 1))])  # x delta, per vertex
        self._plane_normals_t, self._plane_offsets = self.planes[:, :3].T, self.planes[:, 3]
        ids = self._plane_vertex_ids
        # the rows of those vertices: a slice when they are consecutive (no gather per call)
        self._plane_rows_of = slice(int(ids[0]), int(ids[-1]) + 1) \
            if len(ids) and np.array_equal(ids, np.arange(ids[0], ids[-1] + 1)) else ids
        self._key_base = max(len(self.vertex_type), len(self.faces), len(self.edges), len(self.planes)) + 1
        self._staging = Staging(model.device)  # the Gauss-Seidel path's reused arrays
        self._no_time = wp.zeros(1, dtype=wp.float64, device=model.device)  # an unread time array
        self._no_inertia = wp.zeros(1, dtype=wp.mat33d, device=model.device)  # an unread inertia array
        self._cover_scale = 0  # index into COVER_SCALES
        self._launches = RecordedLaunches(model.device)  # and its replayed kernel launches
        self._out = model.state()
        self.last_sweeps = 0
        self.broad_phase = None
        if self.n_vertices and len(self.faces):
            self.broad_phase = BroadPhase(
                self.faces, self.edges, num_vertices=self.n_vertices,
                groups=np.concatenate(groups), self_collision=np.array(self_collision, dtype=bool),
                static=np.array(static, dtype=bool), device=model.device,
            )
            self._narrow = CandidateNarrowPhase(self.broad_phase, **self.ccd_options)
        self.particle_inv_mass = m.particle_inv_mass.numpy() if self.n_particles else np.zeros(0)
        # vertices an impulse can move: rigid ones and unpinned particles
        inv_mass = np.zeros(len(self.vertex_type))
        is_particle = self.vertex_type == _PARTICLE
        inv_mass[is_particle] = self.particle_inv_mass[self.vertex_owner[is_particle]]
        self._mobile_vertex = (self.vertex_type == _BODY) | (inv_mass > 0)
        self.n_bodies = int(m.body_count) if self.n_shape else 0
        # each vertex's particle / body, one past the last for the other kinds (_owner_times)
        self._particle_slot = np.where(self.vertex_type == _PARTICLE, self.vertex_owner, self.n_particles)
        self._body_slot = np.where(self.vertex_type == _BODY, self.vertex_owner, self.n_bodies)
        # the contact times of a plan that no contact changed (read only)
        self._inf_p, self._inf_b = read_only(np.full(self.n_particles, np.inf), np.full(self.n_bodies, np.inf))
        self.body_inv_mass = np.zeros(0)
        self._body_mass = np.zeros(0)
        if self.n_bodies:
            self.body_inv_mass = m.body_inv_mass.numpy()
            self._body_mass = m.body_mass.numpy()
            self._body_inertia = m.body_inertia.numpy().reshape(-1, 3, 3)
        self._particle_inv_mass_w = self._staging.put("inv_mp", self.particle_inv_mass, wp.float64)
        self._body_inv_mass_w = self._staging.put("inv_mb", self.body_inv_mass, wp.float64)
        self.separation = contact_separation(model, mesh)
        self._last = self._last_call = _NO_CONTACTS  # the last call's contacts (restorable / not)
        self.failsafe_count = 0
        self.ccd_events = 0  # approaching CCD hits (contacts added by a CCD round) over the handler's life
        self.untaped_substeps = 0
        self.active_set_repairs = 0
        self.unsettled_active_sets = 0
        # the replay's stages (differentiable=True) and its device copies of the mesh (vertex
        # kinds, owners, local positions, planes), which the Gauss-Seidel path's kernels read too
        self._replay = ContactReplay(
            mesh.vertex_type, mesh.vertex_owner, mesh.local,
            m.particle_inv_mass if self.n_particles else None,
            m.body_inv_mass if self.n_bodies else None,
            m.body_inv_inertia if self.n_bodies else None,
            self.planes, m.friction, m.restitution, m.device,
        )

    # ------------------------------------------------------------------------------------------
    # geometry

    def _pose(self, name: str, particle_q: wp.array | None, body_q: wp.array | None):
        """World positions (V + 1, 3) [m] of the collidable vertices and the dummy vertex at the
        origin, and their lever arms (V + 1, 3) [m] from the owning body's centre of mass (0
        for the others), for the device arrays ``particle_q`` (P,) and ``body_q`` (B,): the
        replay's pose (:func:`kernels.contact.pose_vertices_kernel`) into the handler's buffers
        ``name``.

        Returns:
            (positions, lever arms) on the host (on the CPU views of the buffers, overwritten by
            the next pose into ``name``) and the same two device arrays.
        """
        n, R = self.n_vertices + 1, self._replay
        x = self._staging.empty("x_" + name, n, wp.vec3d)
        lever = self._staging.empty("lever_" + name, n, wp.vec3d)
        self._launches.launch(("pose", name), pose_vertices_kernel, n, [
            particle_q if self.n_particles else R.empty_vec, body_q if self.n_bodies else R.empty_pose,
            R.vertex_type, R.vertex_owner, R.local, x, lever])
        return host(x)[:n], host(lever)[:n], x, lever

    def _pose_substep(self, state_in: State, state_pred: State):
        """:meth:`_pose` of ``state_in`` and of ``state_pred`` and the bodies' world inverse
        inertia tensors at ``state_in`` (``R I^-1 R^T``), in one launch
        (:func:`kernels.contact.pose_substep_kernel`).

        Returns:
            (start positions, start lever arms, their device arrays (2), predicted positions,
            inverse inertia device array): host arrays (V + 1, 3) as :meth:`_pose`'s.
        """
        n, R, B = self.n_vertices + 1, self._replay, self.n_bodies
        empty = self._staging.empty
        x0, lever0 = empty("x_start", n, wp.vec3d), empty("lever_start", n, wp.vec3d)
        x1 = empty("x_predicted", n, wp.vec3d)
        inv_inertia_w = empty("inv_inertia_w", max(B, 1), wp.mat33d)
        P = self.n_particles
        self._launches.launch("pose_substep", pose_substep_kernel, max(n, B), [
            state_in.particle_q if P else R.empty_vec, state_in.body_q if B else R.empty_pose,
            state_pred.particle_q if P else R.empty_vec, state_pred.body_q if B else R.empty_pose,
            R.vertex_type, R.vertex_owner, R.local, self.model.body_inv_inertia if B else self._no_inertia,
            n, B, x0, lever0, x1, inv_inertia_w])
        return host(x0)[:n], host(lever0)[:n], x0, lever0, host(x1)[:n], inv_inertia_w

    def _plan(self, state_in: State, state_pred: State, particle_time, body_time, vp, bv, h: float):
        """End positions of the substep ``h`` [s] for the particles' / bodies' earliest contact
        times ``particle_time`` (P,), ``body_time`` (B,) [s] (inf: none, the prediction of
        ``state_pred`` stays) and their velocities after the impulses ``vp`` (P, 3), ``bv`` (B, 6):
        the replay's time-of-impact integration (:func:`kernels.contact.time_of_impact_position`,
        ``time_of_impact_pose``), then the vertices' positions (:meth:`_pose`).

        Returns:
            (particle positions (P, 3), body poses (B, 7), vertex positions (V + 1, 3)): views
            of the handler's buffers (the next plan overwrites them).
        """
        put, empty, R = self._staging.put, self._staging.empty, self._replay
        P, B, n = self.n_particles, self.n_bodies, self.n_vertices + 1
        x1p = empty("planned_particle_q", P, wp.vec3d)
        bq1 = empty("planned_body_q", B, wp.transformd)
        x1 = empty("x_planned", n, wp.vec3d)
        particles = [state_in.particle_q, state_pred.particle_q, state_pred.particle_qd, put("planned_vp", vp, wp.vec3d),
                     put("particle_time", particle_time, wp.float64)] if P else [R.empty_vec] * 4 + [self._no_time]
        bodies = [state_in.body_q, state_pred.body_q, state_pred.body_qd, put("planned_bv", bv, wp.spatial_vectord),
                  put("body_time", body_time, wp.float64)] if B else \
            [R.empty_pose, R.empty_pose, R.empty_twist, R.empty_twist, self._no_time]
        # with bodies the vertices are posed by a second launch from the planned poses: in the
        # fused one every rigid vertex would integrate its body's pose again (a body of a few
        # hundred vertices made the plan 4x dearer); the same functions, so the same values
        self._launches.launch("plan", planned_substep_kernel, P + B + (0 if B else n), [
            *particles, *bodies, float(h), R.vertex_type, R.vertex_owner, R.local, P, B, x1p, bq1, x1])
        if B:
            x1 = self._pose("planned", x1p if P else None, bq1)[2]
        return (host(x1p)[:P] if P else np.zeros((0, 3)), host(bq1)[:B] if B else np.zeros((0, 7)), host(x1)[:n])

    def _cover(self, x0: np.ndarray, x1_pred: np.ndarray, delta: float) -> None:
        """The substep's broad-phase cover (:meth:`CandidateNarrowPhase.cover`) of the motion
        ``x0 -> x1_pred`` (V, 3) at the current scale (:data:`COVER_SCALES`), which a fresh query
        then moves a step towards its candidate budget."""
        scale = COVER_SCALES[self._cover_scale]
        queries = self._narrow.queries
        self._narrow.cover(x0, x1_pred, COVER_MARGIN * scale * delta, COVER_SLACK * scale * delta, COVER_AHEAD,
                           COVER_AHEAD_LIMIT * scale * delta)
        if self._narrow.queries != queries:
            found = self._narrow.covered_candidates()
            if found < COVER_SPARSE_CANDIDATES:
                self._cover_scale = min(self._cover_scale + 1, len(COVER_SCALES) - 1)
            elif found > COVER_DENSE_CANDIDATES:
                self._cover_scale = max(self._cover_scale - 1, 0)

    def _plane_distances(self, x: np.ndarray) -> np.ndarray | None:
        """Signed distances (K, planes) of the plane-tested vertices (:attr:`_plane_vertex_ids`)
        at positions ``x`` (V + 1, 3) from the planes, or None without planes or such vertices
        (one product per call: the proximity pass and the CCD rounds share the start's)."""
        if not (len(self._plane_vertex_ids) and len(self.planes)):
            return None
        return x[self._plane_rows_of] @ self._plane_normals_t - self._plane_offsets

    def _proximity_rows(self, x0: np.ndarray, x1_pred: np.ndarray, delta: float, plane_d0: np.ndarray | None):
        """The proximity contacts at the start of the substep (positions ``x0`` (V + 1, 3)):
        pairs of primitives whose exact closest points are nearer than ``delta`` [m], then
        movable vertices nearer than ``delta`` to a plane (:meth:`_plane_proximity`).

        The same pass keeps the pairs that the CCD rounds can hit while every vertex ends within
        ``CCD_REACH_SLACK delta`` of its predicted distance from ``x0`` (``x1_pred`` (V + 1,
        3)), which is then all those rounds test (:meth:`CandidateNarrowPhase.near`).
        ``plane_d0``: :meth:`_plane_distances` of ``x0``.

        Returns:
            (kind (C,), pair (C, 2), vertex indices (C, 4)): the mesh pairs (kinds 0, 1) first,
            then the vertex-plane ones (kind 2; :meth:`_start_geometry` relies on the order).
        """
        n = self.n_vertices
        radius = None
        if self._narrow.covered_candidates() >= CCD_REACH_MIN_CANDIDATES:
            step = x1_pred[:n] - x0[:n]
            radius = np.sqrt(np.square(step) @ ONES3) + CCD_REACH_SLACK * delta
            if not radius.max() < np.inf:  # a step past 1e154 m overflows (or NaN): test every candidate
                radius = None
        kind, pair, off, _, idx = self._narrow.near(x0[:n], delta * (1.0 + 1e-9), radius)  # slack: the exact test is here
        near = row_norms(off) < delta
        if not near.all():  # the kernel's test had a hair of slack
            kind, pair, idx = kind[near], pair[near], idx[near]
        if plane_d0 is None:
            return kind, pair, idx
        plane_kind, plane_pair, plane_idx, _ = self._plane_proximity(plane_d0, delta)
        if not len(plane_kind):
            return kind, pair, idx
        return (np.concatenate([kind, plane_kind]), np.concatenate([pair, plane_pair]),
                np.concatenate([idx, plane_idx]))

    def _start_geometry(self, kind, pair, idx, x0: wp.array, lever: wp.array, state_pred: State, h: float):
        """Weights (C, 4), unit normals (C, 3) and target normal velocities (C,) [m/s] of the
        proximity contacts ``kind``, ``pair``, ``idx`` (:meth:`_proximity_rows`) at the start
        positions: :func:`kernels.contact.contact_geometry_kernel`, the replay's definition
        (the offset's direction, or for touching pairs the face / edges' normal turned against
        the relative motion; target ``max(-e min(v_n, 0), rate (delta - d) / h)`` with the
        velocities ``v-`` of ``state_pred``). ``x0``, ``lever``: the start pose's device arrays
        (:meth:`_pose`). Keeps the rows' device arrays for the first solve (``_start_rows``)."""
        c, R = len(kind), self._replay
        put, empty = self._staging.put, self._staging.empty
        out = (empty("geo_toi", c, wp.float64), empty("geo_w", c, wp.vec4d), empty("geo_n", c, wp.vec3d),
               empty("geo_target", c, wp.float64))
        vm_p = state_pred.particle_qd if self.n_particles else R.empty_vec
        vm_b = state_pred.body_qd if self.n_bodies else R.empty_twist
        idx_w, kind_w = put("geo_idx", idx, wp.vec4i), put("geo_kind", kind, wp.int32)
        self._launches.launch("start_geometry", contact_geometry_kernel, c, [
            x0, x0, lever, R.vertex_type, R.vertex_owner, idx_w, kind_w,
            # sources 0 (at the start: no root) and detected fractions 0
            self._staging.zeros("int", c, wp.int32), self._staging.zeros("float", c, wp.float64),
            # the planes of the vertex-plane rows (_proximity_rows puts them last; 0 elsewhere, unused)
            put("geo_plane", np.where(kind == 2, pair[:, 1], 0), wp.int32) if kind[-1] == 2
            else self._staging.zeros("int", c, wp.int32), R.planes,
            vm_p, vm_p, vm_b, vm_b, self._no_time, self._no_time, float(h), float(self.separation),
            float(self.model.restitution), float(SEPARATION_RATE), float(TOUCHING_RELATIVE),
            float(self.max_derivative), 0, *out])
        # the rows as the solve reads them (vertex indices, kinds, weights, normals, targets)
        self._start_rows = (idx_w, kind_w, out[1], out[2], out[3])
        return host(out[1])[:c].copy(), host(out[2])[:c].copy(), host(out[3])[:c].copy()

    def _weights(self, y: np.ndarray, kind: np.ndarray) -> np.ndarray:
        """Signed weights (C, 4) of the exact closest points of the pairs (``kind`` (C,): 0
        vertex-face, 1 edge-edge, 2 vertex-plane) at positions ``y`` (C, 4, 3): side A positive
        (sum 1), side B negative (sum -1); :func:`kernels.contact.pair_weights`, the definition
        the replay and the narrow phase use."""
        if not len(y):
            return np.zeros((0, 4))
        put = self._staging.put
        out = self._staging.empty("weights", len(y), wp.vec4d)
        self._launches.launch("weights", pair_weights_kernel, len(y),
                              [put("kind", kind, wp.int32), put("y", np.reshape(y, (-1, 3)), wp.vec3d), out])
        return host(out)[: len(y)].copy()

    def _plane_proximity(self, dist: np.ndarray, delta: float):
        """Movable vertices (unpinned particles, rigid vertices) closer than ``delta`` to (or
        behind) a plane at the start, from their :meth:`_plane_distances` ``dist`` there: (kind
        2, pair (vertex, plane), vertex indices (vertex, dummy x3), signed distance)."""
        verts = self._plane_vertex_ids
        # the integrator's plane stage leaves particles at exactly delta, which this product
        # may round to a hair below: such a particle is no contact (without the slack a resting
        # cloth joined the solve on every substep, all of it in one replayed system)
        v, k = np.nonzero(dist < self._plane_threshold * delta)
        if not len(v):  # the common case: nothing near a plane
            return _NO_PLANE_ROWS
        return self._plane_rows(verts[v], k) + (dist[v, k],)

    def _plane_rows(self, vertex: np.ndarray, plane: np.ndarray):
        kind = np.full(len(vertex), 2, dtype=np.int64)
        pair = np.empty((len(vertex), 2), dtype=np.int64)
        pair[:, 0], pair[:, 1] = vertex, plane
        idx = np.full((len(vertex), 4), self.n_vertices, dtype=np.int64)
        idx[:, 0] = vertex
        return kind, pair, idx

    def _ccd_candidates(self, x0: np.ndarray, x1: np.ndarray, plane_d0: np.ndarray | None):
        """Hits of the straight paths ``x0 -> x1`` (with the dummy vertex last): vertex-face,
        edge-edge (broad + narrow phase at zero thickness) and vertex-plane (a movable vertex
        ends behind the plane, moving inwards).

        Returns:
            (kind (C,), pair (C, 2), vertex indices (C, 4), time of impact as a fraction of the
            substep (C,), source (C,): the narrow phase's (0 start, 1-3 cubic slot, 4 collinear,
            5 advancement) or 6 for planes). ``plane_d0``: :meth:`_plane_distances` of ``x0``.
        """
        n = self.n_vertices
        kinds, pairs, idxs, tois, sources = [], [], [], [], []
        kind, pair, toi, source, idx = self._narrow.ccd(x0[:n], x1[:n], 0.0)
        if len(kind):
            kinds.append(kind)
            pairs.append(pair)
            idxs.append(idx)
            tois.append(toi)
            sources.append(source)
        if plane_d0 is not None:
            verts = self._plane_vertex_ids
            d0 = plane_d0
            d1 = self._plane_distances(x1)
            behind = d1 < 0.0
            v, k = np.nonzero(behind & (d1 < d0)) if behind.any() else (_NONE_INDEX, _NONE_INDEX)
            if len(v):
                kind, pair, idx = self._plane_rows(verts[v], k)
                kinds.append(kind)
                pairs.append(pair)
                idxs.append(idx)
                tois.append(np.clip(d0[v, k] / (d0[v, k] - d1[v, k]), 0.0, 1.0))
                sources.append(np.full(len(v), 6, dtype=np.int64))
        if not kinds:
            return _NO_HITS
        if len(kinds) == 1:
            return kinds[0], pairs[0], idxs[0], tois[0], sources[0]
        return (np.concatenate(kinds), np.concatenate(pairs), np.concatenate(idxs), np.concatenate(tois),
                np.concatenate(sources))

    # ------------------------------------------------------------------------------------------
    # velocities and impulses

    def _vertex_velocities(self, idx, vp, bv, r0):
        """(C, 4, 3) velocities of the contacts' vertices for particle velocities ``vp`` and body
        twists ``bv`` (angular, linear), lever arms ``r0`` of the start pose."""
        vel = np.zeros(idx.shape + (3,))
        t = self.vertex_type[idx]
        o = self.vertex_owner[idx]
        p = t == _PARTICLE
        if len(vp):
            vel[p] = vp[o[p]]
        b = t == _BODY
        if len(bv):
            body = o[b]
            vel[b] = bv[body, 3:6] + cross(bv[body, :3], r0[idx[b] - self.shape_offset])
        return vel

    def _velocities_at(self, idx, toi, t_p, t_b, before, after, r0):
        """(C, 4, 3) vertex velocities at each contact's time ``toi`` [s]: the ``before``
        (particle, body) velocities (``v-``) while it precedes its owner's earliest contact time
        (``t_p``, ``t_b``), the ``after`` ones from then on."""
        v_before = self._vertex_velocities(idx, *before, r0)
        v_after = self._vertex_velocities(idx, *after, r0)
        t = self.vertex_type[idx]
        o = self.vertex_owner[idx]
        owner_t = np.full(idx.shape, np.inf)
        p = t == _PARTICLE
        owner_t[p] = t_p[o[p]]
        b = t == _BODY
        owner_t[b] = t_b[o[b]]
        return np.where((toi[:, None] < owner_t)[..., None], v_before, v_after)

    def _approach(self, idx, w, n, vel, x0, x1, h, at_end):
        """Normal relative velocities (C,) at the contacts and whether each CCD hit approaches:
        by its velocities at ``t*`` or along the straight paths ``x0 -> x1`` checked by CCD
        (their mean velocity over the substep decides whether the primitives pass through). A
        contact already in the set at the very end of the substep (``at_end`` (C,) bool) that
        leaves faster than the separation speed ``delta / h`` is judged by its velocities only:
        its path ends on the contact instead of passing through it, and judging it by the path
        re-added it every round until the impact-zone fail-safe froze it (an elastic bounce off a
        wall stopped dead). Slower ones (inelastic contacts) keep the path test and the fail-safe."""
        vn = np.einsum("cd,cd->c", np.einsum("ck,ckd->cd", w, vel), n)
        vn_path = np.einsum("cd,cd->c", np.einsum("ck,ckd->cd", w, (x1[idx] - x0[idx]) / h), n)
        # below -APPROACH_EPS relative: rounding of an exactly separating pair is not an approach
        eps = APPROACH_EPS * (np.abs(vel).max(axis=(1, 2)) + self._sep_speed)
        leaving = at_end & (vn > self._sep_speed)
        return vn, (vn < -eps) | ((vn_path < -eps) & ~leaving)

    def _solve(self, cs: _Contacts, vp, bv, lever: wp.array, inv_inertia_w: wp.array, rows=None):
        """Projected Gauss-Seidel on the contact set (:func:`kernels.contact.solve_contacts_kernel`):
        updates ``vp``, ``bv`` (the velocities after the impulses) in place and the accumulated
        impulses of ``cs``. ``lever`` (V + 1,) and ``inv_inertia_w`` (B,) (at least one row):
        device arrays of the vertices' lever arms (:meth:`_pose`) and the bodies' world inverse
        inertia tensors at the start pose. Its other arrays are the handler's reused buffers (no
        allocation). ``rows``: device arrays (vertex indices, kinds, weights, normals, targets)
        that hold the set's rows already (:meth:`_start_geometry`'s for the first set)."""
        if len(cs) == 0:
            return
        put = self._staging.put
        if rows is None:
            rows = (put("idx", cs.idx, wp.vec4i), put("kind", cs.kind, wp.int32), put("w", cs.w, wp.vec4d),
                    put("n", cs.n, wp.vec3d), put("target", cs.target, wp.float64))
        P, B, C = len(vp), len(bv), len(cs)
        # without particles (bodies) no contact has a particle (rigid) vertex, so the kernel
        # never writes the shared zero input passed for their velocities
        vp_w = put("vp", vp, wp.vec3d) if P else self._replay.empty_vec
        lin_w, ang_w = (put("lin", bv[:, 3:6], wp.vec3d), put("ang", bv[:, 0:3], wp.vec3d)) if B else \
            (self._replay.empty_vec, self._replay.empty_vec)
        jn = put("jn", cs.jn, wp.float64)
        jt = put("jt", cs.jt, wp.vec3d)
        sweeps = self._staging.empty("sweeps", 1, wp.int32)
        tol = SOLVER_TOLERANCE * SEPARATION_RATE * self._sep_speed
        idx_w, kind_w, w_w, n_w, target_w = rows
        self._launches.launch("solve", solve_contacts_kernel, 1, [
            len(cs), idx_w, w_w, n_w, target_w, kind_w,
            self._replay.vertex_type, self._replay.vertex_owner,
            lever, 0,  # indexed by vertex
            self._particle_inv_mass_w, self._body_inv_mass_w, inv_inertia_w,
            float(self.model.friction), int(SOLVER_ITERATIONS), float(tol),
            # scratch: the contacts' constants over the sweeps
            self._staging.empty("contact_mass", len(cs), wp.float64),
            self._staging.empty("contact_particles", len(cs), wp.vec4i),
            self._staging.empty("contact_bodies", len(cs), wp.vec2i),
            self._staging.empty("contact_body_weight", len(cs), wp.vec2d),
            self._staging.empty("contact_lever", 2 * len(cs), wp.vec3d),
            vp_w, lin_w, ang_w, jn, jt, sweeps,
        ])
        if P:
            vp[:] = host(vp_w)[:P]
        if B:
            bv[:, 3:6] = host(lin_w)[:B]
            bv[:, 0:3] = host(ang_w)[:B]
        cs.jn, cs.jt = host(jn)[:C].copy(), host(jt)[:C].copy()
        self.last_sweeps = int(host(sweeps)[0])

    def _body_inertia_w(self, body_q):
        """World inertia tensors R I R^T of the bodies at poses ``body_q``."""
        if not self.n_bodies:
            return np.zeros((0, 3, 3))
        rot = quat_to_matrix(body_q[:, 3:7])
        return rot @ self._body_inertia @ np.swapaxes(rot, 1, 2)

    def _owner_times(self, cs: _Contacts, n_p: int, n_b: int):
        """Earliest time of impact [s] per particle / body among the contacts of the set (inf
        where none): its velocity switches from ``v-`` to ``v+`` then."""
        # one slot past the owners takes the other kinds' vertices (no masks by kind)
        t_p = np.full(n_p + 1, np.inf)
        t_b = np.full(n_b + 1, np.inf)
        if len(cs):
            idx = cs.idx.ravel()
            at_start = not cs.toi.any()  # proximity contacts only (resting contact): all at 0
            toi = None if at_start else np.repeat(cs.toi, 4)
            if n_p:
                p = cs.w.ravel() != 0
                if at_start:
                    t_p[self._particle_slot[idx[p]]] = 0.0
                else:
                    np.minimum.at(t_p, self._particle_slot[idx[p]], toi[p])
            if n_b:
                if at_start:
                    t_b[self._body_slot[idx]] = 0.0
                else:
                    np.minimum.at(t_b, self._body_slot[idx], toi)
        return t_p[:n_p], t_b[:n_b]

    # ------------------------------------------------------------------------------------------

    _COUNTERS = ("failsafe_count", "ccd_events", "untaped_substeps", "active_set_repairs", "unsettled_active_sets")

    @property
    def last_contacts(self) -> np.ndarray:
        """(C, 3) contact points [m] of the last call (see the class docstring)."""
        return self._last.contacts()[0]

    @property
    def last_normals(self) -> np.ndarray:
        """(C, 3) unit normals of the last call's contacts."""
        return self._last.contacts()[1]

    @property
    def last_times(self) -> np.ndarray:
        """(C,) times of impact [s] of the last call's contacts, from the start of its substep."""
        return self._last.contacts()[2]

    @property
    def last_contact_count(self) -> int:
        """How many contacts received an impulse in the last call (``len(last_times)``, without
        working out the contact points)."""
        return self._last.count

    @property
    def last_body_particles(self) -> np.ndarray:
        """(K,) the particles that shared a contact with a rigid body's vertex in the last call
        (the implicit integrator must not prescribe their motion in a re-solve: the body would not
        feel the reaction). Not put back by :meth:`restore_stats`."""
        return self._last_call.body_particles()

    def save_stats(self) -> dict:
        """The statistics (life counters, last call's contacts), for :meth:`restore_stats` after
        calls whose result an integrator discards (a trial pass, a rejected substep)."""
        stats = {c: getattr(self, c) for c in self._COUNTERS + ("_last",)}
        stats["largest_system"] = self._replay.largest_system
        return stats

    def restore_stats(self, stats: dict) -> None:
        """Puts back the statistics of :meth:`save_stats`."""
        for c, v in stats.items():
            if c == "largest_system":
                self._replay.largest_system = v
            else:
                setattr(self, c, v)

    def _check_states(self, state_in: State, state_pred: State) -> None:
        """Raises a ValueError naming the array of ``state_in`` / ``state_pred`` with fewer rows
        than the model's particles / bodies (the kernels would read past its end)."""
        for label, state in (("state_in", state_in), ("state_pred", state_pred)):
            for name, count in (("particle_q", self.n_particles), ("particle_qd", self.n_particles),
                                ("body_q", self.n_bodies), ("body_qd", self.n_bodies)):
                if count and (getattr(state, name) is None or getattr(state, name).shape[0] < count):
                    have = 0 if getattr(state, name) is None else getattr(state, name).shape[0]
                    raise ValueError(f"{label}.{name}: {have} rows, the model has {count}")

    def _note_contacts(self, record: _CallContacts) -> None:
        """Makes ``record`` the last call's contacts (:attr:`last_contacts`, ...)."""
        self._last = self._last_call = record

    def __call__(self, state_in: State, state_pred: State, h: float) -> State | None:
        self._note_contacts(_NO_CONTACTS)
        if self.broad_phase is None:
            return None
        self._check_states(state_in, state_pred)
        if self.differentiable:
            return self._call_replayed(state_in, state_pred, h)
        P, B = self.n_particles, self.n_bodies
        # host views of the states (read only here: the result goes to the handler's own State)
        x0p = host(state_in.particle_q)[:P] if P else np.zeros((0, 3))
        bq0 = host(state_in.body_q) if B else np.zeros((0, 7))
        vp_minus = host(state_pred.particle_qd)[:P] if P else np.zeros((0, 3))
        bv_minus = host(state_pred.body_qd) if B else np.zeros((0, 6))
        x1p_pred = host(state_pred.particle_q)[:P] if P else np.zeros((0, 3))
        bq1_pred = host(state_pred.body_q) if B else np.zeros((0, 7))
        vp, bv = vp_minus.copy(), bv_minus.copy()
        # the vertices at the start (with the rigid ones' lever arms) and the predicted end
        x0, lever0, x0_w, lever0_w, x1_pred, inv_inertia_w = self._pose_substep(state_in, state_pred)
        r0 = lever0[self.shape_offset:self.static_offset]
        inf_p, inf_b = self._inf_p, self._inf_b
        zones = None  # the fail-safe's impact zones, made when it first acts (rare)
        delta = self.separation
        self._sep_speed = delta / h
        e = self.model.restitution
        cs = _Contacts(self._key_base)

        def plan():
            """End positions (particles, body poses, all vertices) of the current velocities and
            contact times, and the contact times per particle / body."""
            if not len(cs) and zones is None:
                return x1p_pred, bq1_pred, inf_p, inf_b, x1_pred  # nothing changed the prediction
            t_p, t_b = self._owner_times(cs, P, B)
            if zones is not None:  # an impact zone moves rigidly over the whole substep
                t_p[zones.particles] = 0.0
                t_b[zones.bodies] = 0.0
            x1p, bq1, x1 = self._plan(state_in, state_pred, t_p, t_b, vp, bv, h)
            return x1p, bq1, t_p, t_b, x1

        # one broad-phase query for the proximity pass and the CCD rounds while their motion
        # stays within the margin of the predicted one (CandidateNarrowPhase.cover)
        self._cover(x0[:-1], x1_pred[:-1], delta)
        # 1. proximity contacts at the start of the substep: the mesh and the plane ones, added
        # and solved together
        plane_d0 = self._plane_distances(x0)
        kind, pair, idx = self._proximity_rows(x0, x1_pred, delta, plane_d0)
        if len(kind):
            w, n, target = self._start_geometry(kind, pair, idx, x0_w, lever0_w, state_pred, h)
            cs.add(kind, pair, idx, w, n, np.zeros(len(kind)), target, copy=False, distinct=True)  # fresh arrays
            self._solve(cs, vp, bv, lever0_w, inv_inertia_w, self._start_rows)  # the same rows, on the device

        # 2-5. CCD rounds on the planned motion
        failsafe = False
        for iteration in itertools.count():
            x1p, bq1, t_p, t_b, x1 = plan()
            kind, pair, idx, toi, _ = self._ccd_candidates(x0, x1, plane_d0)
            if len(kind) == 0:
                break
            ee_mask = kind == 1
            frac = toi[:, None, None]
            y = x0[idx] + frac * (x1[idx] - x0[idx])
            w = self._weights(y, kind)
            n = self._normals(idx, x0, y, w, ee_mask)
            on_plane = kind == 2
            if on_plane.any():
                n[on_plane] = self.planes[pair[on_plane, 1], :3]
            vel = self._velocities_at(idx, toi * h, t_p, t_b, (vp_minus, bv_minus), (vp, bv), r0)
            vn, approaching = self._approach(idx, w, n, vel, x0, x1, h, cs.at_end(kind, pair, toi * h, h))
            if not approaching.any():
                break
            if iteration >= self.max_iterations:
                # fail-safe: rigid impact zones (Provot 1997, Bridson et al. 2002): everything
                # joined by a still-approaching contact moves as one rigid body (momentum kept;
                # at rest when the zone holds a static or pinned vertex) over the whole substep
                failsafe = True
                if zones is None:
                    zones = _ImpactZones(P, B, self.particle_inv_mass)
                if not zones.merge(self.vertex_type[idx[approaching]], self.vertex_owner[idx[approaching]]):
                    break  # only contacts inside rigidly moving zones remain (rounding)
                zones.rigid_velocities(x0p, vp, bq0, bv, self.particle_inv_mass,
                                       self._body_mass, self._body_inertia_w(bq0))
                continue
            sel = approaching
            self.ccd_events += int(sel.sum())
            target = np.maximum(-e * vn[sel], SEPARATION_RATE * delta / h)
            cs.add(kind[sel], pair[sel], idx[sel], w[sel], n[sel], toi[sel] * h, target)
            self._solve(cs, vp, bv, lever0_w, inv_inertia_w)
        if failsafe:
            self.failsafe_count += 1
        # the result is the last round's plan: every exit of the rounds follows a plan() with
        # nothing changed after it (no contact added, no velocity solved, no zone grown)
        self._note_contacts(_CallContacts(cs, x0, x1, h, self.vertex_type))
        if len(cs) == 0 and not failsafe:
            return None
        # the result in the handler's own State (reused: the integrator copies it out)
        out = self._out
        if P:
            upload(out.particle_q, x1p)
            upload(out.particle_qd, vp)
        if B:
            upload(out.body_q, bq1)
            upload(out.body_qd, bv)
        return State(
            particle_q=out.particle_q if P else state_pred.particle_q,
            particle_qd=out.particle_qd if P else state_pred.particle_qd,
            body_q=out.body_q if B else state_pred.body_q,
            body_qd=out.body_qd if B else state_pred.body_qd,
        )

    def _call_replayed(self, state_in: State, state_pred: State, h: float) -> State | None:
        """The response as decisions on the host and a taped replay on the device
        (:class:`collision.replay.ContactReplay`): the result is the replay's, exact for the
        decided contact set (impulses from the active set's equations, not Gauss-Seidel sweeps),
        and differentiable when a ``wp.Tape`` is recording. The fail-safe's impact zones are
        taped too: their membership is decided here, their momentum-conserving rigid motion is
        replayed (:meth:`collision.replay.ContactReplay.zone_velocities`), so every substep is
        taped and ``untaped_substeps`` stays 0."""
        R = self._replay
        R.begin()  # the previous call's results were copied by the integrator: its arrays are free
        P, B = self.n_particles, self.n_bodies
        m = self.model
        nv = self.n_vertices
        xq0 = state_in.particle_q if P else None
        bq0_w = state_in.body_q if B else None
        vm_p = state_pred.particle_qd if P else None
        vm_b = state_pred.body_qd if B else None
        X0, L0 = R.pose(xq0, bq0_w)
        inv_I = R.world_inverse_inertia(bq0_w)
        x0 = X0.numpy()
        vp_minus = vm_p.numpy() if P else np.zeros((0, 3))
        bv_minus = vm_b.numpy() if B else np.zeros((0, 6))
        vp, bv = vp_minus.copy(), bv_minus.copy()
        r0 = L0.numpy()[self.shape_offset:self.shape_offset + self.n_shape] if self.n_shape else np.zeros((0, 3))
        zones = _ImpactZones(P, B, self.particle_inv_mass)
        delta = self.separation
        self._sep_speed = delta / h
        mu = float(m.friction)
        cs = _Contacts(self._key_base)
        st = {"dev": None, "vp": vm_p, "vb": vm_b}
        tol = SOLVER_TOLERANCE * SEPARATION_RATE * self._sep_speed
        def owners():
            t_p, t_b = self._owner_times(cs, P, B)
            po = np.full(P, -1, dtype=np.int64)
            bo = np.full(B, -1, dtype=np.int64)
            if len(cs):
                rows = np.repeat(np.arange(len(cs)), 4)
                toi = np.repeat(cs.toi, 4)
                t = self.vertex_type[cs.idx].ravel()
                o = self.vertex_owner[cs.idx].ravel()
                # the contact whose time is the owner's earliest; among ties (same t*: a corner
                # on a face diagonal is several pairs) one whose time the replay differentiates,
                # written last so it wins
                order = np.argsort(np.repeat(cs.timed, 4), kind="stable")
                rows, toi, t, o = rows[order], toi[order], t[order], o[order]
                p = (t == _PARTICLE) & (cs.w.ravel()[order] != 0)
                p[p] = toi[p] == t_p[o[p]]
                po[o[p]] = rows[p]
                b = t == _BODY
                b[b] = toi[b] == t_b[o[b]]
                bo[o[b]] = rows[b]
            po[zones.particles] = -2
            bo[zones.bodies] = -2
            return po, bo, t_p, t_b

        def plan():
            po, bo, t_p, t_b = owners()
            toi = st["dev"][0] if st["dev"] is not None else R.take(1, wp.float64, grad=False)
            X1p, BQ1 = R.integrate(xq0, state_pred.particle_q if P else None, vm_p, st["vp"], bq0_w,
                                   state_pred.body_q if B else None, vm_b, st["vb"], po, bo, toi, h)
            return X1p, BQ1, t_p, t_b

        def geometry(kind, pair, idx, frac, source, X1, t_p, t_b):
            rows = {"pairs": idx, "kinds": kind, "sources": source, "detected": frac,
                    "plane_ids": np.where(kind == 2, pair[:, 1], 0)}
            out = R.geometry(X0, X1, L0, rows, vm_p, st["vp"], vm_b, st["vb"], t_p, t_b, h, delta,
                             SEPARATION_RATE, TOUCHING_RELATIVE, self.max_derivative,
                             bool(self.ccd_options))  # a generated narrow phase numbers roots its own way
            return out, [a.numpy()[: len(kind)] for a in out]

        def add(sel, out, host, kind, pair, idx, source):
            toi_h, w_h, n_h, tg_h = host
            new_index, keep_toi, keep_tg = cs.add(kind[sel], pair[sel], idx[sel], w_h[sel], n_h[sel], toi_h[sel],
                                                  tg_h[sel], np.isin(source[sel], (1, 2, 3, 6)))
            pos = np.flatnonzero(sel)
            full = np.where(new_index >= 0, pos[np.maximum(new_index, 0)], -1)
            st["dev"] = R.merge(st["dev"], (out[0], out[3], out[1], out[2]), full, keep_toi, keep_tg)

        def exact():
            # decide: the active set from projected Gauss-Seidel, then replay the exact normal
            # solve and repair the set (drop pulling contacts, add violated ones) until it holds
            with paused_tape():
                self._solve(cs, vp, bv, L0, inv_I)
            mobile = ((cs.w != 0) & self._mobile_vertex[cs.idx]).any(axis=1)
            active = (cs.jn > 0) & mobile
            taped = active.copy()  # the set whose solve the tape holds (the first trial's)
            tape = active_tape()
            for iteration in range(ACTIVE_SET_ITERATIONS):
                share = self._friction_share(cs, active) if mu > 0 else None
                # the first trial is recorded (usually it is the final one); repair trials stay off
                # the tape (their O(n^2) matrices would be kept to the end)
                with (contextlib.nullcontext() if iteration == 0 else paused_tape()):
                    vp_d, vb_d, normal = R.solve(st["dev"], cs.idx, cs.kind, active, L0, inv_I, vm_p, vm_b, share)
                if iteration == 0:
                    recorded = (vp_d, vb_d, normal)
                jn = np.einsum("cd,cd->c", normal.numpy()[: len(cs)], cs.n)
                vrel = np.einsum("ck,ckd->cd", cs.w, self._vertex_velocities(
                    cs.idx, vp_d.numpy() if P else vp, vb_d.numpy() if B else bv, r0))
                vn = np.einsum("cd,cd->c", vrel, cs.n)
                scale = max(float(np.abs(jn).max()), 1e-300)
                new = active.copy()
                new[active & (jn < -1e-9 * scale)] = False
                new[~active & mobile & (vn < cs.target - tol)] = True
                if (new == active).all():
                    break
                if iteration == ACTIVE_SET_ITERATIONS - 1:
                    self.unsettled_active_sets += 1
                    break  # the last trial's set stands, taped or not: one forward function
                active = new
                self.active_set_repairs += 1
            if tape is not None and not np.array_equal(taped, active):
                # the replay of the final active set, recorded
                share = self._friction_share(cs, active) if mu > 0 else None
                vp_d, vb_d, normal = R.solve(st["dev"], cs.idx, cs.kind, active, L0, inv_I, vm_p, vm_b, share)
                jn = np.einsum("cd,cd->c", normal.numpy()[: len(cs)], cs.n)
            elif tape is not None:
                # the repairs came back to the first trial's set: its recorded solve (the same
                # values) is the one the tape continues from, not the last, unrecorded trial
                vp_d, vb_d, normal = recorded
            if P:
                st["vp"] = vp_d
                vp[:] = vp_d.numpy()
            if B:
                st["vb"] = vb_d
                bv[:] = vb_d.numpy()
            cs.jn = np.where(active, jn, 0.0)
            cs.jt = np.zeros_like(cs.jt)

        inf_p, inf_b = np.full(P, np.inf), np.full(B, np.inf)
        # 1. proximity contacts at the start of the substep
        with paused_tape():  # decisions: off the tape
            # one broad-phase query while the rounds' motion stays near the predicted one
            x1_pred = self._pose("predicted", state_pred.particle_q, state_pred.body_q)[0]
            self._cover(x0[:nv], x1_pred[:nv], delta)
            plane_d0 = self._plane_distances(x0)
            kind, pair, idx = self._proximity_rows(x0, x1_pred, delta, plane_d0)
        if len(kind):
            zero = np.zeros(len(kind))
            out, host = geometry(kind, pair, idx, zero, np.zeros(len(kind), dtype=np.int64), X0, inf_p, inf_b)
            add(np.ones(len(kind), dtype=bool), out, host, kind, pair, idx, np.zeros(len(kind), dtype=np.int64))
            exact()

        # 2-5. CCD rounds on the planned motion
        failsafe = False
        X1 = None
        for iteration in itertools.count():
            X1p, BQ1, t_p, t_b = plan()
            X1, _ = R.pose(X1p if P else None, BQ1 if B else None)
            x1 = X1.numpy()
            with paused_tape():  # decisions: off the tape
                kind, pair, idx, frac, source = self._ccd_candidates(x0, x1, plane_d0)
            if len(kind) == 0:
                break
            # times off the cubic (start, collinear, advancement) enter as constants
            source = np.where(np.isin(source, (1, 2, 3, 6)), source, 4)
            out, host = geometry(kind, pair, idx, frac, source, X1, t_p, t_b)
            toi, w, n, _ = host
            vel = self._velocities_at(idx, toi, t_p, t_b, (vp_minus, bv_minus), (vp, bv), r0)
            _, approaching = self._approach(idx, w, n, vel, x0, x1, h, cs.at_end(kind, pair, toi, h))
            if not approaching.any():
                break
            if iteration >= self.max_iterations:
                failsafe = True
                if not zones.merge(self.vertex_type[idx[approaching]], self.vertex_owner[idx[approaching]]):
                    break
                # the zones' momentum-conserving rigid motion, on the tape (membership decided
                # above); the host copies follow for the next round's decisions
                particle_zone, body_zone, n_zones = zones.labels()
                st["vp"], st["vb"] = R.zone_velocities(st["vp"], st["vb"], particle_zone, body_zone, n_zones, xq0,
                                                       bq0_w, m.body_mass if B else None,
                                                       m.body_inertia if B else None)
                if P:
                    vp[:] = st["vp"].numpy()
                if B:
                    bv[:] = st["vb"].numpy()
                continue
            self.ccd_events += int(approaching.sum())
            add(approaching, out, host, kind, pair, idx, source)
            exact()
        if failsafe:
            self.failsafe_count += 1
        if len(cs) == 0 and not failsafe:
            return None
        X1p, BQ1, _, _ = plan()
        x1 = R.pose(X1p if P else None, BQ1 if B else None)[0].numpy() if (cs.jn > 0).any() else None
        self._note_contacts(_CallContacts(cs, x0, x1, h, self.vertex_type))
        return State(
            particle_q=X1p if P else state_pred.particle_q,
            particle_qd=st["vp"] if P else state_pred.particle_qd,
            body_q=BQ1 if B else state_pred.body_q,
            body_qd=st["vb"] if B else state_pred.body_qd,
        )

    def _friction_share(self, cs: _Contacts, active: np.ndarray) -> np.ndarray:
        """Per contact: one over the largest number of active contacts that any particle or body
        it moves takes part in (friction impulses of one pass are applied together)."""
        P = self.n_particles
        t = self.vertex_type[cs.idx]
        o = self.vertex_owner[cs.idx]
        node = np.where((t == _PARTICLE) & (cs.w != 0), o, np.where(t == _BODY, P + o, -1))
        rows = np.repeat(np.arange(len(cs)), 4).reshape(-1, 4)
        sel = active[:, None] & (node >= 0)
        pairs = np.unique(np.column_stack([rows[sel], node[sel]]), axis=0) if sel.any() else np.zeros((0, 2), dtype=np.int64)
        counts = np.bincount(pairs[:, 1], minlength=P + self.n_bodies + 1) if len(pairs) else np.zeros(P + self.n_bodies + 1)
        per_slot = np.where(node >= 0, counts[np.maximum(node, 0)], 0)
        most = np.maximum(per_slot.max(axis=1), 1)
        return 1.0 / most

    @staticmethod
    def _normals(idx, x0, y, w, edge_edge):
        """Unit contact normals (side B -> side A) of CCD hits at positions ``y`` (C, 4, 3): the
        face normal (vertex-face) or the edges' cross product (edge-edge), oriented by the
        offset at the start; where those degenerate, the start offset itself."""
        c = len(idx)
        n = np.zeros((c, 3))
        vf = ~edge_edge
        n[vf] = cross(y[vf, 2] - y[vf, 1], y[vf, 3] - y[vf, 1])
        n[edge_edge] = cross(y[edge_edge, 1] - y[edge_edge, 0], y[edge_edge, 3] - y[edge_edge, 2])
        rel = np.einsum("ck,ckd->cd", w, x0[idx])
        norm = row_norms(n)
        scale = np.max(np.abs(y - y.mean(1, keepdims=True)), axis=(1, 2))
        bad = norm <= 1e-12 * scale * scale
        n[bad] = rel[bad]
        norm = row_norms(n)
        n = np.divide(n, norm[:, None], out=np.tile([0.0, 0.0, 1.0], (c, 1)), where=norm[:, None] > 0)
        flip = np.einsum("cd,cd->c", n, rel) < 0
        n[flip] *= -1
        return n


class _ImpactZones:
    """Union-find over particles (nodes 0..P-1), bodies (P..P+B-1) and "the world" (P+B: static
    vertices and pinned particles) for the rigid-impact-zone fail-safe of one substep."""

    def __init__(self, n_particles: int, n_bodies: int, particle_inv_mass: np.ndarray) -> None:
        self.P, self.B = n_particles, n_bodies
        self.parent = np.arange(n_particles + n_bodies + 1)
        self.world = n_particles + n_bodies
        self.pinned = np.flatnonzero(particle_inv_mass[:n_particles] == 0)
        self.particles = np.zeros(n_particles, dtype=bool)
        self.bodies = np.zeros(n_bodies, dtype=bool)

    def _find(self, i: int) -> int:
        root = i
        while self.parent[root] != root:
            root = self.parent[root]
        while self.parent[i] != root:
            self.parent[i], i = root, self.parent[i]
        return root

    def merge(self, vertex_type: np.ndarray, vertex_owner: np.ndarray) -> bool:
        """Joins the owners of each row of (C, 4) vertex types / owners into one zone; returns
        whether any zone grew."""
        grew = False
        nodes = np.where(vertex_type == _PARTICLE, vertex_owner,
                         np.where(vertex_type == _BODY, self.P + vertex_owner, self.world))
        pinned = np.isin(vertex_owner, self.pinned) & (vertex_type == _PARTICLE)
        nodes = np.where(pinned, self.world, nodes)
        for row in nodes:
            root = self._find(int(row[0]))
            for node in row[1:]:
                other = self._find(int(node))
                if other != root:
                    grew = True
                    # the world stays a root so that zones touching it are recognised
                    if other == self.world:
                        self.parent[root] = other
                        root = other
                    else:
                        self.parent[other] = root
        for node in np.unique(nodes):
            if node < self.P:
                grew |= not self.particles[node]
                self.particles[node] = True
            elif node < self.world:
                grew |= not self.bodies[node - self.P]
                self.bodies[node - self.P] = True
        return bool(grew)

    def labels(self):
        """The zones as ints for the taped replay (:meth:`collision.replay.ContactReplay.zone_velocities`):
        per particle and per body -1 (in no zone), -2 (in the zone touching the world: at rest)
        or the index of its free zone; and the number of free zones."""
        particle_zone = np.full(self.P, -1, dtype=np.int64)
        body_zone = np.full(self.B, -1, dtype=np.int64)
        members_p = np.flatnonzero(self.particles)
        members_b = np.flatnonzero(self.bodies)
        roots = np.array([self._find(int(i)) for i in members_p] + [self._find(int(self.P + i)) for i in members_b],
                         dtype=np.int64)
        free = np.unique(roots[roots != self.world])
        index = np.where(roots == self.world, -2, np.searchsorted(free, roots))
        particle_zone[members_p] = index[: len(members_p)]
        body_zone[members_b] = index[len(members_p):]
        return particle_zone, body_zone, len(free)

    def rigid_velocities(self, x0p, vp, bq0, bv, particle_inv_mass, body_mass, body_inertia_w) -> None:
        """Overwrites the velocities of zone members with their zone's rigid motion (in place;
        the Gauss-Seidel response's fail-safe, not taped; the replayed response records the
        same motion on the tape with :meth:`collision.replay.ContactReplay.zone_velocities`)."""
        members_p = np.flatnonzero(self.particles)
        members_b = np.flatnonzero(self.bodies)
        roots_p = np.array([self._find(int(i)) for i in members_p], dtype=np.int64)
        roots_b = np.array([self._find(int(self.P + i)) for i in members_b], dtype=np.int64)
        for root in np.unique(np.concatenate([roots_p, roots_b])):
            zp = members_p[roots_p == root]
            zb = members_b[roots_b == root]
            if root == self.world:
                vp[zp] = 0.0
                bv[zb] = 0.0
                continue
            mp = np.divide(1.0, particle_inv_mass[zp], out=np.zeros(len(zp)), where=particle_inv_mass[zp] > 0)
            mb = body_mass[zb]
            mass = mp.sum() + mb.sum()
            centre = (mp @ x0p[zp] + mb @ bq0[zb, :3]) / mass
            momentum = mp @ vp[zp] + mb @ bv[zb, 3:6]
            rp = x0p[zp] - centre
            rb = bq0[zb, :3] - centre
            angular = (np.cross(rp, vp[zp]) * mp[:, None]).sum(0) + (np.cross(rb, bv[zb, 3:6]) * mb[:, None]).sum(0)
            angular += np.einsum("bij,bj->i", body_inertia_w[zb], bv[zb, :3])
            eye = np.eye(3)
            inertia = np.einsum("p,pij->ij", mp, (rp * rp).sum(1)[:, None, None] * eye - rp[:, :, None] * rp[:, None, :])
            inertia += body_inertia_w[zb].sum(0)
            inertia += np.einsum("b,bij->ij", mb, (rb * rb).sum(1)[:, None, None] * eye - rb[:, :, None] * rb[:, None, :])
            omega = np.linalg.pinv(inertia) @ angular  # pinv: a zone of collinear particles
            linear = momentum / mass
            vp[zp] = linear + np.cross(omega, rp)
            bv[zb, 3:6] = linear + np.cross(omega, rb)
            bv[zb, :3] = omega

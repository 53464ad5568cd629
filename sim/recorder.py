"""Rerun recording of a simulation run: meshes, poses, contacts and metrics per frame.

:class:`SimRecorder` follows the project's rerun conventions (``docs/design.md``) on top of
:class:`sim.logging.RerunLogger`: deterministic recording id, no wall-clock timelines, timelines
``frame`` (sequence) and ``sim_time`` (duration, seconds).

Entity tree (``<i>`` is a decimal index):

* ``/world``: static ``ViewCoordinates`` (right-handed, z up).
* ``/world/cloth``: ``Mesh3D`` of the cloth triangles. ``triangle_indices`` (and colour) are
  logged **static, once**; each frame logs only ``vertex_positions`` (all particles, so the
  indices stay valid).
* ``/world/particles``: ``Points3D`` per frame of the particles no triangle uses (only if any).
* ``/world/bodies/<i>``: rigid body ``i``'s surface mesh in its body frame (static, once) and a
  ``Transform3D`` per frame (translation = centre of mass, quaternion ``xyzw`` from ``body_q``).
* ``/world/static/<i>``: static mesh connected component ``i`` (world frame, static, once). The
  model stores all static meshes in one array, so a mesh made of disjoint pieces appears as
  several entities.
* ``/world/planes/<i>``: ground plane ``i`` as a square quad (static, once), centred on the
  projection of the scene's initial bounding-box centre, half side
  ``max(10 m, 2 x bounding-box diagonal)``.
* ``/world/contacts/points`` (``Points3D``, labels ``toi=...`` when times of impact are given,
  hidden by default), ``/world/contacts/normals`` (``Arrows3D`` from the points along the normals):
  every frame once contacts were recorded (empty when a frame has none, so stale contacts never
  linger).
* ``/metrics/<name>``: ``Scalars`` per frame, one per entry of ``metrics``; frames with contacts
  also get ``/metrics/contacts/count`` and, when times of impact are given,
  ``/metrics/contacts/time_of_impact`` (the frame's earliest).
* ``/status``: static ``TextDocument`` written when the recorder closes: ``complete: N frames`` or
  ``interrupted after N frames: <ExceptionType>: <message>``.

Default blueprint: a 3D view of ``/world`` next to a time-series view of ``/metrics``.

Interruption (the chosen behaviour): the recording goes to a hidden temporary file that replaces
``path`` only when the recorder closes. On a clean close the file holds every frame. If the
``with`` block is left by an exception (including ``KeyboardInterrupt``), the frames recorded so
far are flushed, ``/status`` says ``interrupted ...``, the file is renamed to ``NAME.partial.rrd``
beside ``path`` (a complete, readable recording of those frames; ``path`` itself keeps whatever it
held) and the exception propagates. The stream is flushed after every frame, so a hard kill
(SIGKILL) leaves ``path`` untouched and the frames so far in the hidden ``.<name>.<pid>.tmp`` file
next to it (the next recording written beside it removes that file). A :class:`SimRecorder`
attached to a caller's logger (:meth:`SimRecorder.on_logger`) leaves the file's fate to that
logger.

Example:
    >>> with SimRecorder("run.rrd", model, application_id="drape", seed=0) as rec:  # doctest: +SKIP
    ...     for k in range(steps):
    ...         integrator.step(state, next_state, dt); state, next_state = next_state, state
    ...         rec.record(k, (k + 1) * dt, state, metrics={"energy": energy(state)})
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from types import TracebackType

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from sim.logging import RerunLogger
from sim.model import Model, State
from sim.penetration import state_positions, vertex_components
from core.buffers import rows

__all__ = ["Contacts", "SimRecorder", "default_blueprint"]

PLANE_MIN_HALF_SIZE = 10.0
"""Smallest half side [m] of the quad drawn for a ground plane."""

CLOTH_COLOR = (70, 130, 200, 255)
BODY_COLOR = (220, 140, 60, 255)
STATIC_COLOR = (150, 150, 150, 255)
PLANE_COLOR = (120, 160, 120, 160)
CONTACT_COLOR = (230, 40, 40, 255)


@dataclass
class Contacts:
    """Contacts of one frame.

    Attributes:
        points: (N, 3) contact positions [m].
        normals: (N, 3) contact normals (any length; drawn normalised), or None.
        toi: (N,) times of impact (fraction of the step or seconds, as the caller uses them),
            a scalar for all contacts, or None.
    """

    points: np.ndarray
    normals: np.ndarray | None = None
    toi: np.ndarray | float | None = None


def _as_contacts(c) -> Contacts:
    if isinstance(c, Contacts):
        raw = (c.points, c.normals, c.toi)
    elif isinstance(c, Mapping):
        raw = (c.get("points"), c.get("normals"), c.get("toi"))
    else:
        raw = (getattr(c, "points", None), getattr(c, "normals", None), getattr(c, "toi", None))
    points, normals, toi = raw
    if points is None:
        raise ValueError("contacts: need 'points' ((N, 3) positions)")
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3) if np.size(points) else np.zeros((0, 3))
    n = None
    if normals is not None:
        n = np.asarray(normals, dtype=np.float64)
        n = n.reshape(-1, 3) if n.size else np.zeros((0, 3))
        if n.shape != p.shape:
            raise ValueError(f"contacts: normals have shape {n.shape}, points {p.shape}")
    t = None
    if toi is not None:
        t = np.asarray(toi, dtype=np.float64)
        t = np.full(len(p), float(t)) if t.ndim == 0 else t.reshape(-1)
        if t.shape != (len(p),):
            raise ValueError(f"contacts: toi has shape {t.shape}, expected ({len(p)},)")
    return Contacts(p, n, t)


def default_blueprint() -> rrb.Blueprint:
    """3D view of ``/world`` beside a time-series view of ``/metrics``."""
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(name="world", origin="/world"),
            rrb.TimeSeriesView(name="metrics", origin="/metrics"),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )



class SimRecorder:
    """Writes one simulation run to a ``.rrd`` file (see the module docstring for the layout).

    Use it as a context manager (or call :meth:`close`). The static scene (topology, body meshes,
    static meshes, planes, blueprint) is logged on construction; :meth:`record` logs one frame.

    Args:
        path: Destination ``.rrd``; its folder must exist.
        model: The :class:`sim.model.Model` being simulated.
        application_id: Rerun application id.
        seed: Run seed (part of the deterministic recording id).
        recording_name: Recording name (default: ``application_id``).
        contact_normal_length: Drawn length of contact normals [m] (default: 5% of the initial
            scene bounding-box diagonal).
        flush_every: Flush the stream to disk every this many frames (default 1: every frame).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        model: Model,
        *,
        application_id: str = "tunnelsim",
        seed: int = 0,
        recording_name: str | None = None,
        contact_normal_length: float | None = None,
        flush_every: int = 1,
    ) -> None:
        logger = RerunLogger(
            path,
            application_id=application_id,
            recording_name=recording_name or application_id,
            seed=seed,
            keep_partial=True,
        )
        self._init(model, contact_normal_length, flush_every)
        self._logger = logger
        self._owns = True
        logger.__enter__()
        try:
            self._log_static(blueprint=True)
        except BaseException as e:
            logger.keep_partial = False  # nothing useful written: leave no file
            logger.__exit__(type(e), e, e.__traceback__)
            raise

    @classmethod
    def on_logger(
        cls,
        logger: RerunLogger,
        model: Model,
        *,
        blueprint: bool = True,
        contact_normal_length: float | None = None,
        flush_every: int = 0,
    ) -> SimRecorder:
        """A recorder logging into an already open :class:`RerunLogger` (e.g. the scene CLI's).

        The caller keeps ownership of the file: :meth:`close` writes ``/status`` but neither
        flushes nor finalises the logger.

        Args:
            logger: An open logger.
            model: The model.
            blueprint: Send :func:`default_blueprint` as the default blueprint.
            contact_normal_length: As in the constructor.
            flush_every: Flush every this many frames (0: never; the logger flushes on exit).
        """
        self = cls.__new__(cls)
        self._init(model, contact_normal_length, flush_every)
        self._logger = logger
        self._owns = False
        self._log_static(blueprint=blueprint)
        return self

    # ------------------------------------------------------------------ set-up
    def _init(self, model: Model, contact_normal_length: float | None, flush_every: int) -> None:
        if int(flush_every) < 0:
            raise ValueError(f"flush_every must be >= 0, got {flush_every}")
        self.model = model
        self.flush_every = int(flush_every)
        self.frames = 0
        self.closed = False
        self._contacts_seen = False
        self.particle_count = int(model.particle_count)
        self.body_count = int(model.body_count)
        mesh = self.mesh = model.collision_mesh
        fo = mesh.face_offsets
        self.tris = mesh.faces[fo[0]:fo[1]]
        used = np.zeros(self.particle_count, dtype=bool)
        used[self.tris.reshape(-1)] = True
        self.loose_particles = np.flatnonzero(~used)
        allp = mesh.positions(rows(model.particle_q, (3,)), rows(model.body_q, (7,)))
        if not len(allp):
            allp = np.zeros((1, 3))
        self.bounds = (allp.min(axis=0), allp.max(axis=0))
        diag = float(np.linalg.norm(self.bounds[1] - self.bounds[0]))
        self.scene_diagonal = diag
        if contact_normal_length is None:
            contact_normal_length = max(0.05 * diag, 1e-3)
        if not (math.isfinite(contact_normal_length) and contact_normal_length > 0):
            raise ValueError(f"contact_normal_length must be finite and > 0, got {contact_normal_length}")
        self.contact_normal_length = float(contact_normal_length)

    def _log_static(self, *, blueprint: bool) -> None:
        rec = self._logger.stream
        m = self.model
        if blueprint:
            self._logger.send_blueprint(default_blueprint())
        rec.log("/world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        if len(self.tris):
            rec.log(
                "/world/cloth",
                rr.Mesh3D.from_fields(triangle_indices=self.tris.astype(np.uint32), albedo_factor=CLOTH_COLOR),
                static=True,
            )
        if len(self.loose_particles):
            rec.log("/world/particles", rr.Points3D.from_fields(colors=CLOTH_COLOR), static=True)

        mesh, fo = self.mesh, self.mesh.face_offsets
        sv, sb = mesh.shape_local, mesh.shape_body
        sf = mesh.faces[fo[1]:fo[2]] - mesh.shape_offset
        for b in range(self.body_count):
            vid = np.flatnonzero(sb == b)
            faces = sf[np.all(np.isin(sf, vid), axis=1)]
            local = np.searchsorted(vid, faces)
            rec.log(
                f"/world/bodies/{b}",
                rr.Mesh3D(
                    vertex_positions=sv[vid], triangle_indices=local.astype(np.uint32), albedo_factor=BODY_COLOR
                ),
                static=True,
            )

        gv = mesh.static_vertices
        gf = mesh.faces[fo[2]:fo[3]] - mesh.static_offset
        comp = vertex_components(gf, len(gv))
        self.static_mesh_count = int(comp.max()) + 1 if len(gv) else 0
        face_comp = comp[gf[:, 0]] if len(gf) else np.zeros(0, np.int64)
        for c in range(self.static_mesh_count):
            vid = np.flatnonzero(comp == c)
            local = np.searchsorted(vid, gf[face_comp == c])
            rec.log(
                f"/world/static/{c}",
                rr.Mesh3D(
                    vertex_positions=gv[vid], triangle_indices=local.astype(np.uint32), albedo_factor=STATIC_COLOR
                ),
                static=True,
            )

        planes = rows(m.planes, (4,)) if m.plane_count else np.zeros((0, 4))
        centre = 0.5 * (self.bounds[0] + self.bounds[1])
        half = max(PLANE_MIN_HALF_SIZE, 2.0 * self.scene_diagonal)
        for k, pl in enumerate(planes):
            n, off = pl[:3] / np.linalg.norm(pl[:3]), pl[3]
            c0 = centre - (np.dot(n, centre) - off) * n
            helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
            u = np.cross(n, helper)
            u /= np.linalg.norm(u)
            v = np.cross(n, u)
            quad = c0 + half * np.array([-u - v, u - v, u + v, -u + v])
            rec.log(
                f"/world/planes/{k}",
                rr.Mesh3D(
                    vertex_positions=quad,
                    triangle_indices=np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32),
                    vertex_normals=np.tile(n, (4, 1)),
                    albedo_factor=PLANE_COLOR,
                ),
                static=True,
            )

    # ------------------------------------------------------------------ per frame
    def record(
        self,
        frame: int,
        sim_time: float,
        state: State | Mapping,
        contacts: Contacts | Mapping | object | None = None,
        metrics: Mapping[str, float] | None = None,
    ) -> None:
        """Logs one frame.

        Args:
            frame: Value on the ``frame`` timeline.
            sim_time: Simulated time [s] (timeline ``sim_time``).
            state: A :class:`sim.model.State` or a mapping with ``particle_q`` (P, 3) and
                ``body_q`` (B, 7) arrays.
            contacts: None, a :class:`Contacts`, a mapping or an object with ``points``,
                ``normals`` and ``toi`` (see :class:`Contacts`).
            metrics: Name -> scalar, logged to ``/metrics/<name>`` (names may contain ``/``).
        """
        if self.closed:
            raise RuntimeError("SimRecorder is closed")
        if isinstance(frame, bool) or not isinstance(frame, (int, np.integer)):
            raise ValueError(f"frame must be an integer, got {frame!r}")
        st = float(sim_time)
        if not math.isfinite(st):
            raise ValueError(f"sim_time must be finite, got {sim_time!r}")
        pq, bq = state_positions(state)
        if len(pq) != self.particle_count:
            raise ValueError(f"state has {len(pq)} particles, the model {self.particle_count}")
        if len(bq) != self.body_count:
            raise ValueError(f"state has {len(bq)} bodies, the model {self.body_count}")
        c = None if contacts is None else _as_contacts(contacts)
        names = []
        for name, value in (metrics or {}).items():
            if not isinstance(name, str) or not name or name.startswith("/") or name.endswith("/"):
                raise ValueError(f"metric names must be non-empty relative paths, got {name!r}")
            names.append((name, float(value)))

        rec = self._logger.stream
        rec.set_time("frame", sequence=int(frame))
        rec.set_time("sim_time", duration=st)
        if len(self.tris):
            rec.log("/world/cloth", rr.Mesh3D.from_fields(vertex_positions=pq))
        if len(self.loose_particles):
            rec.log("/world/particles", rr.Points3D(pq[self.loose_particles]))
        for b in range(self.body_count):
            q = bq[b, 3:]
            q = q / np.linalg.norm(q)
            rec.log(
                f"/world/bodies/{b}",
                rr.Transform3D(translation=bq[b, :3], quaternion=rr.Quaternion(xyzw=q)),
            )
        if c is not None or self._contacts_seen:
            self._log_contacts(rec, c)
        for name, value in names:
            rec.log(f"/metrics/{name}", rr.Scalars(value))
        self.frames += 1
        if self.flush_every and self.frames % self.flush_every == 0:
            rec.flush()

    def _log_contacts(self, rec: rr.RecordingStream, c: Contacts | None) -> None:
        self._contacts_seen = True
        if c is None:
            c = Contacts(np.zeros((0, 3)))
        labels = [] if c.toi is None else [f"toi={t:.6g}" for t in c.toi]  # [] clears old labels
        rec.log(
            "/world/contacts/points",
            rr.Points3D(c.points, colors=CONTACT_COLOR, labels=labels, show_labels=False),
        )
        if c.normals is not None:
            ln = np.linalg.norm(c.normals, axis=1, keepdims=True)
            vec = np.divide(c.normals, ln, out=np.zeros_like(c.normals), where=ln > 0) * self.contact_normal_length
            rec.log("/world/contacts/normals", rr.Arrows3D(origins=c.points, vectors=vec, colors=CONTACT_COLOR))
        else:
            rec.log("/world/contacts/normals", rr.Arrows3D(origins=np.zeros((0, 3)), vectors=np.zeros((0, 3))))
        rec.log("/metrics/contacts/count", rr.Scalars(float(len(c.points))))
        if c.toi is not None and len(c.toi):
            rec.log("/metrics/contacts/time_of_impact", rr.Scalars(float(np.min(c.toi))))

    # ------------------------------------------------------------------ closing
    def close(
        self,
        exc_type: type[BaseException] | None = None,
        exc: BaseException | None = None,
        tb: TracebackType | None = None,
    ) -> None:
        """Writes ``/status`` and, if this recorder owns the file, flushes and finalises it.

        Called by ``__exit__`` with the exception (if any); calling it again does nothing.
        """
        if self.closed:
            return
        self.closed = True
        try:
            if exc_type is None:
                status = f"complete: {self.frames} frames"
            else:
                status = f"interrupted after {self.frames} frames: {exc_type.__name__}: {exc}"
            self._logger.log_text("/status", status)
        finally:
            if self._owns:
                self._logger.__exit__(exc_type, exc, tb)

    def __enter__(self) -> SimRecorder:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close(exc_type, exc, tb)

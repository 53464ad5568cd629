"""Physics validation: classic rigid-body and cloth checks against closed forms and references.

    python benchmarks/physics.py [--quick] [--only NAME,...] [--out-dir benchmarks/results]

Every check runs for both collision responses of
:class:`sim.contact.response.ImpulseCollisionHandler` (``gauss_seidel``: ``differentiable=False``;
``replayed``: ``differentiable=True``, the response :func:`sim.rollout.rollout` uses) and at
4, 8, 16 and 32 substeps of a 1/60 s step (``--quick``: 8 substeps only, and shorter runs where a
check says so). Unless a check says otherwise: thickness 1 mm, boxes of half extent 0.1 m at
500 kg/m^3, gravity (0, 0, -9.81) m/s^2, the semi-implicit integrator.

Each check returns :class:`Record` rows (one per measured quantity): ``name``, ``variant``,
``quantity``, ``response``, ``substeps``, ``expected`` (text) and ``expected_value``,
``measured``, ``tolerance`` (absolute, or relative to ``expected_value`` where ``mode`` is
``"rel"``), ``passed``, ``reference`` (the closed form or reference) and ``details``. The
tolerances are the targets the physics must meet, not what the simulator reaches today: a FAIL
row is a finding, not a bug of the check.

Measurements: yaw is the twist angle about the world z axis of the rotation from the body's
initial orientation (swing-twist decomposition of ``q q0^-1``, quaternions from ``body_q``);
drift is the horizontal (tangential on a slope) displacement of the centre of mass from its
start, the largest over all sampled steps; post-impact velocities are read a fixed time after
the impact in zero gravity (nothing else happens in between); the fail-safe is the handler's
``failsafe_count``. Samples are taken at the end of every 1/60 s step.

Writes ``<out-dir>/physics.md`` (the table) and ``<out-dir>/physics.json``
(``{"checks": [record, ...], ...}``); one progress line per check run on stderr.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)  # before this folder: benchmarks/sim.py must not shadow the sim package

from benchmarks import report  # noqa: E402

__all__ = [
    "CHECKS", "DT", "RESPONSES", "Record", "SUBSTEPS_FULL", "SUBSTEPS_QUICK", "main", "run_suite",
    "check_flat_drop_plane", "check_flat_drop_static_box", "check_flat_drop_rigid_box", "check_slope_static",
    "check_slope_sliding", "check_rest_plane", "check_rest_box", "check_stack", "check_restitution_sweep",
    "check_head_on", "check_free_rotation", "check_cloth_flat_box", "check_cloth_hanging", "check_cloth_on_sphere",
    "check_sliding_friction", "check_sphere_bounce", "check_ball_bounce", "check_ball_roll", "check_ball_head_on",
]

DT = 1.0 / 60.0
"""Step length [s]."""
THICKNESS = 1e-3
"""Contact thickness [m] (the handler's separation)."""
DENSITY = 500.0
"""Box density [kg/m^3]."""
BOX_HALF = 0.1
"""Default box half extent [m]."""
GRAVITY = 9.81
RESPONSES = {"gauss_seidel": False, "replayed": True}
"""Response name -> ``ImpulseCollisionHandler(differentiable=...)``."""
SUBSTEPS_FULL = (4, 8, 16, 32)
SUBSTEPS_QUICK = (8,)
RESTITUTION_GAPS = (0.05, 0.0505, 0.051, 0.0515, 0.052)
"""Initial face-to-face gaps [m] of the restitution sweep: at 1 m/s the (zero-thickness) impact
falls at t = gap / (1 m/s); 0.05 m is exactly 3 steps (a substep boundary at every substep count);
at 8 substeps (2.083 mm per substep) the others fall at phases 0.24, 0.48, 0.72, 0.96 of a
substep."""


# --------------------------------------------------------------------------------------------
# records
# --------------------------------------------------------------------------------------------


@dataclass
class Record:
    """One measured quantity of one check at one setting.

    ``passed``: ``|measured - expected_value| <= tolerance`` (``mode="abs"``) or
    ``<= tolerance * |expected_value|`` (``mode="rel"``); False when ``measured`` is not finite.
    """

    name: str
    response: str
    substeps: int
    quantity: str
    expected: str
    expected_value: float
    measured: float
    tolerance: float
    passed: bool
    reference: str
    variant: str = ""
    mode: str = "abs"
    error: float = math.nan
    details: dict = field(default_factory=dict)

    @property
    def label(self) -> str:
        """``name [variant] quantity`` (the table's check column)."""
        v = f" [{self.variant}]" if self.variant else ""
        return f"{self.name}{v}: {self.quantity}"

    def as_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["label"] = self.label
        return d


def _record(name: str, response: str, substeps: int, quantity: str, measured: float, *, expected_value: float = 0.0,
            tolerance: float, expected: str, reference: str, mode: str = "abs", variant: str = "",
            **details) -> Record:
    measured = float(measured)
    expected_value = float(expected_value)
    error = abs(measured - expected_value)
    if mode == "abs":
        passed = error <= tolerance
    elif mode == "rel":
        passed = error <= tolerance * abs(expected_value)
        error = error / abs(expected_value) if expected_value else math.inf
    else:
        raise ValueError(f"mode must be 'abs' or 'rel', got {mode!r}")
    passed = bool(passed and math.isfinite(measured))
    return Record(name=name, response=response, substeps=int(substeps), quantity=quantity, expected=expected,
                  expected_value=expected_value, measured=measured, tolerance=float(tolerance), passed=passed,
                  reference=reference, variant=variant, mode=mode, error=float(error), details=_plain(details))


def _plain(value):
    """JSON-friendly copy (numpy scalars and arrays to Python)."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    return value


def _check_response(response: str) -> bool:
    if response not in RESPONSES:
        raise ValueError(f"response must be one of {tuple(RESPONSES)}, got {response!r}")
    return RESPONSES[response]


# --------------------------------------------------------------------------------------------
# quaternions (x, y, z, w) and measurements
# --------------------------------------------------------------------------------------------


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products ``a b`` of quaternions (..., 4) in (x, y, z, w) order."""
    av, aw = a[..., :3], a[..., 3:4]
    bv, bw = b[..., :3], b[..., 3:4]
    v = aw * bv + bw * av + np.cross(av, bv)
    w = aw * bw - np.sum(av * bv, axis=-1, keepdims=True)
    return np.concatenate([v, w], axis=-1)


def _quat_conj(q: np.ndarray) -> np.ndarray:
    return np.concatenate([-q[..., :3], q[..., 3:4]], axis=-1)


def relative_rotation(q: np.ndarray, q0: np.ndarray) -> np.ndarray:
    """``q q0^-1`` (world-frame rotation from ``q0`` to ``q``), normalised, with ``w >= 0``."""
    r = _quat_mul(np.asarray(q, dtype=np.float64), _quat_conj(np.asarray(q0, dtype=np.float64)))
    r = r / np.linalg.norm(r, axis=-1, keepdims=True)
    return np.where(r[..., 3:4] < 0.0, -r, r)


def twist_angle(q: np.ndarray, q0: np.ndarray, axis=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Signed angle [rad] of the twist about the world ``axis`` of the rotation from ``q0`` to
    ``q`` (swing-twist decomposition; the yaw for ``axis = z``), in (-pi, pi]."""
    r = relative_rotation(q, q0)
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    return 2.0 * np.arctan2(r[..., :3] @ a, r[..., 3])


def rotation_angle(q: np.ndarray, q0: np.ndarray) -> np.ndarray:
    """Angle [rad] of the rotation from ``q0`` to ``q``, in [0, pi]."""
    r = relative_rotation(q, q0)
    return 2.0 * np.arctan2(np.linalg.norm(r[..., :3], axis=-1), r[..., 3])


def _rot_matrix(q: np.ndarray) -> np.ndarray:
    from core.rotation import quat_to_matrix

    return quat_to_matrix(q)


def _quat_axis_angle(axis, angle: float) -> tuple:
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    s = math.sin(angle / 2.0)
    return (a[0] * s, a[1] * s, a[2] * s, math.cos(angle / 2.0))


# --------------------------------------------------------------------------------------------
# running a scene
# --------------------------------------------------------------------------------------------


class Run:
    """A model stepped by the semi-implicit integrator with an :class:`ImpulseCollisionHandler`
    of ``response``; samples (time, body_q, body_qd, particle_q, particle_qd) at every step's end.

    Args:
        builder: the scene's :class:`sim.builder.ModelBuilder` (finalised here).
        response: ``"gauss_seidel"`` or ``"replayed"``.
        substeps: substeps per step.
        dt: step [s].
        particle_qd: optional initial particle velocities (P, 3) replacing the model's.
        exact_gravity: the semi-implicit integrator's exact ballistic update.
    """

    def __init__(self, builder, response: str, substeps: int, dt: float = DT, particle_qd=None,
                 exact_gravity: bool = False) -> None:
        from sim.contact.response import ImpulseCollisionHandler
        from sim.integrators import make_integrator

        differentiable = _check_response(response)
        self.model = builder.finalize()
        self.integrator = make_integrator(self.model, exact_gravity=exact_gravity)
        self.handler = ImpulseCollisionHandler(self.model, differentiable=differentiable)
        self.integrator.collision_handler = self.handler
        self.state, self.next = self.model.state(), self.model.state()
        if particle_qd is not None:
            import warp as wp

            self.state.particle_qd = wp.array(np.asarray(particle_qd, dtype=np.float64), dtype=wp.vec3d,
                                              device=self.model.device)
        self.dt, self.substeps = float(dt), int(substeps)
        self.steps = 0
        self._samples: list[dict] = []
        self._sample()

    def _sample(self) -> None:
        s = self.state.numpy()
        s["t"] = self.steps * self.dt
        for key in ("body_q", "body_qd", "particle_q", "particle_qd"):
            if not np.all(np.isfinite(s[key])):
                raise FloatingPointError(f"non-finite {key} after {self.steps} steps")
        self._samples.append(s)

    def step(self, n: int = 1) -> Run:
        for _ in range(int(n)):
            self.integrator.step(self.state, self.next, self.dt, self.substeps)
            self.state, self.next = self.next, self.state
            self.steps += 1
            self._sample()
        return self

    def run_for(self, seconds: float) -> Run:
        """Steps until ``seconds`` of simulated time have passed (rounded to whole steps)."""
        return self.step(max(int(round(seconds / self.dt)), 1))

    def _stack(self, key: str) -> np.ndarray:
        return np.stack([s[key] for s in self._samples])

    @property
    def t(self) -> np.ndarray:
        return np.array([s["t"] for s in self._samples])

    @property
    def body_q(self) -> np.ndarray:
        """(N+1, B, 7)."""
        return self._stack("body_q")

    @property
    def body_qd(self) -> np.ndarray:
        """(N+1, B, 6): angular, linear (world)."""
        return self._stack("body_qd")

    @property
    def particle_q(self) -> np.ndarray:
        return self._stack("particle_q")

    @property
    def particle_qd(self) -> np.ndarray:
        return self._stack("particle_qd")

    @property
    def failsafe_count(self) -> int:
        return int(self.handler.failsafe_count)


def scene_builder(gravity=(0.0, 0.0, -GRAVITY), restitution: float = 0.0, friction: float = 0.5,
             thickness: float = THICKNESS):
    from sim.builder import ModelBuilder

    b = ModelBuilder(gravity=gravity)
    b.set_contact(restitution=restitution, friction=friction, thickness=thickness)
    return b


def add_box(b, half, pos, rot=None, velocity=(0.0, 0.0, 0.0), angular_velocity=(0.0, 0.0, 0.0),
             density: float = DENSITY) -> int:
    from sim.mesh_io import box_mesh

    return b.add_rigid_body(*box_mesh(half), density=density, pos=pos, rot=rot, velocity=velocity,
                            angular_velocity=angular_velocity)


def _horizontal_drift(p: np.ndarray) -> np.ndarray:
    """Horizontal distance of the positions (N, 3) from the first."""
    d = p[:, :2] - p[0, :2]
    return np.sqrt(np.sum(d * d, axis=-1))


def _tangential(p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Distance within the plane of normal ``n`` of the positions (N, 3) from the first."""
    d = p - p[0]
    d = d - np.outer(d @ n, n)
    return np.sqrt(np.sum(d * d, axis=-1))


# --------------------------------------------------------------------------------------------
# 1-3: flat drops
# --------------------------------------------------------------------------------------------

DROP_HALF = 0.05
DROP_HEIGHT = 0.4


def check_flat_drop_plane(response: str = "replayed", substeps: int = 8, *, friction: float = 0.0,
                          restitution: float = 0.5, seconds: float = 1.5, height: float = DROP_HEIGHT) -> list[Record]:
    """A box (half extent 0.05 m), axis aligned, centre of mass at ``height`` m, dropped onto the
    ground plane z = 0: by symmetry it bounces straight up and down, so its angular velocity and
    horizontal drift stay 0 (tolerance 1e-9)."""
    b = scene_builder(restitution=restitution, friction=friction)
    add_box(b, DROP_HALF, (0.0, 0.0, height))
    b.add_ground_plane()
    run = Run(b, response, substeps).run_for(seconds)
    bq, bqd = run.body_q[:, 0], run.body_qd[:, 0]
    omega = np.linalg.norm(bqd[:, :3], axis=-1)
    drift = _horizontal_drift(bq[:, :3])
    yaw = twist_angle(bq[:, 3:], bq[0, 3:])
    variant = f"mu={friction:g}, e={restitution:g}, {seconds:g} s"
    ref = ("symmetry: a flat, axis-aligned box dropped on a plane gets only vertical impulses "
           "(no torque, no tangential force), so omega = 0 and the drift is 0")
    common = dict(variant=variant, reference=ref, failsafe=run.failsafe_count, max_yaw=float(np.max(np.abs(yaw))),
                  final_z=float(bq[-1, 2]))
    return [
        _record("flat_drop_plane", response, substeps, "max omega norm [rad/s]", omega.max(), tolerance=1e-9,
                expected="0", **common),
        _record("flat_drop_plane", response, substeps, "max horizontal drift [m]", drift.max(), tolerance=1e-9,
                expected="0", **common),
    ]


def check_flat_drop_static_box(response: str = "replayed", substeps: int = 8, *, friction: float = 0.0,
                               restitution: float = 0.5, seconds: float = 1.5,
                               height: float = DROP_HEIGHT) -> list[Record]:
    """The same box dropped flat onto a static box mesh (half extent 0.2 m, centred at the
    origin: top face z = 0.2 m; no ground plane): yaw and horizontal drift stay 0 (1e-9)."""
    from sim.mesh_io import box_mesh

    b = scene_builder(restitution=restitution, friction=friction)
    add_box(b, DROP_HALF, (0.0, 0.0, height))
    b.add_static_mesh(*box_mesh(0.2))
    run = Run(b, response, substeps).run_for(seconds)
    bq, bqd = run.body_q[:, 0], run.body_qd[:, 0]
    yaw = np.abs(twist_angle(bq[:, 3:], bq[0, 3:]))
    drift = _horizontal_drift(bq[:, :3])
    variant = f"mu={friction:g}, e={restitution:g}, {seconds:g} s"
    ref = ("symmetry: the box lands flat in the middle of the static box's top face (its corners on the "
           "top triangles, its bottom edges across the top face's diagonal): only vertical impulses, yaw = 0, "
           "drift = 0")
    common = dict(variant=variant, reference=ref, failsafe=run.failsafe_count,
                  max_omega=float(np.linalg.norm(bqd[:, :3], axis=-1).max()),
                  max_rotation=float(rotation_angle(bq[:, 3:], bq[0, 3:]).max()), final_z=float(bq[-1, 2]))
    return [
        _record("flat_drop_static_box", response, substeps, "max abs yaw [rad]", yaw.max(), tolerance=1e-9,
                expected="0", **common),
        _record("flat_drop_static_box", response, substeps, "max horizontal drift [m]", drift.max(), tolerance=1e-9,
                expected="0", **common),
    ]


def check_flat_drop_rigid_box(response: str = "replayed", substeps: int = 8, *, friction: float = 0.0,
                              restitution: float = 0.5, seconds: float = 1.5,
                              height: float = DROP_HEIGHT) -> list[Record]:
    """The same box dropped flat onto a free box (half extent 0.1 m) resting on the ground plane
    (bottom face at the contact separation): yaw and horizontal drift of both stay 0 (1e-9)."""
    b = scene_builder(restitution=restitution, friction=friction)
    top = add_box(b, DROP_HALF, (0.0, 0.0, height))
    bottom = add_box(b, BOX_HALF, (0.0, 0.0, BOX_HALF + THICKNESS))
    b.add_ground_plane()
    run = Run(b, response, substeps).run_for(seconds)
    bq, bqd = run.body_q, run.body_qd
    variant = f"mu={friction:g}, e={restitution:g}, {seconds:g} s"
    ref = ("symmetry: both boxes axis aligned and centred on one vertical line; every impulse is vertical, "
           "so neither box turns or drifts")
    out = []
    for body, who in ((top, "top"), (bottom, "bottom")):
        yaw = np.abs(twist_angle(bq[:, body, 3:], bq[0, body, 3:]))
        drift = _horizontal_drift(bq[:, body, :3])
        common = dict(variant=variant, reference=ref, failsafe=run.failsafe_count,
                      max_omega=float(np.linalg.norm(bqd[:, body, :3], axis=-1).max()),
                      max_rotation=float(rotation_angle(bq[:, body, 3:], bq[0, body, 3:]).max()),
                      final_z=float(bq[-1, body, 2]))
        out.append(_record("flat_drop_rigid_box", response, substeps, f"{who} box max abs yaw [rad]", yaw.max(),
                           tolerance=1e-9, expected="0", **common))
        out.append(_record("flat_drop_rigid_box", response, substeps, f"{who} box max horizontal drift [m]",
                           drift.max(), tolerance=1e-9, expected="0", **common))
    return out


# --------------------------------------------------------------------------------------------
# 4-5: slope
# --------------------------------------------------------------------------------------------

SLOPE_DEG = 20.0


def _slope_run(response: str, substeps: int, mu: float, angle_deg: float, seconds: float):
    """A box (half 0.1 m) flat on a plane through the origin tilted by ``angle_deg`` about y
    (normal (sin a, 0, cos a), downhill (cos a, 0, -sin a)), its centre of mass at the contact
    separation; at rest."""
    a = math.radians(angle_deg)
    n = np.array([math.sin(a), 0.0, math.cos(a)])
    down = np.array([math.cos(a), 0.0, -math.sin(a)])
    b = scene_builder(friction=mu)
    add_box(b, BOX_HALF, n * (BOX_HALF + THICKNESS), rot=_quat_axis_angle((0.0, 1.0, 0.0), a))
    b.add_ground_plane(normal=n, offset=0.0)
    run = Run(b, response, substeps).run_for(seconds)
    return run, n, down


def check_slope_static(response: str = "replayed", substeps: int = 8, *, mu: float = 0.5, seconds: float = 4.0,
                       angle_deg: float = SLOPE_DEG) -> list[Record]:
    """A box at rest on a 20 degree slope with mu >= tan 20 = 0.364 stays put: its largest
    displacement along the slope over the run is 0 (tolerance 1e-6 m)."""
    run, n, down = _slope_run(response, substeps, mu, angle_deg, seconds)
    bq, bqd = run.body_q[:, 0], run.body_qd[:, 0]
    along = _tangential(bq[:, :3], n)
    normal = (bq[:, :3] - bq[0, :3]) @ n
    ref = (f"static friction: mu = {mu:g} >= tan {angle_deg:g} deg = {math.tan(math.radians(angle_deg)):.4f}, "
           "so the box sticks (Coulomb) and does not move along the slope")
    return [_record("slope_static", response, substeps, "max displacement along the slope [m]", along.max(),
                    tolerance=1e-6, expected="0 (sticks)", reference=ref, variant=f"mu={mu:g}, {seconds:g} s",
                    final_along_downhill=float((bq[-1, :3] - bq[0, :3]) @ down),
                    max_normal_settle=float(np.abs(normal).max()),
                    max_rotation=float(rotation_angle(bq[:, 3:], bq[0, 3:]).max()),
                    final_speed=float(np.linalg.norm(bqd[-1, 3:])), failsafe=run.failsafe_count)]


def check_slope_sliding(response: str = "replayed", substeps: int = 8, *, mu: float = 0.2, seconds: float = 2.0,
                        fit_after: float = 0.2, angle_deg: float = SLOPE_DEG) -> list[Record]:
    """A box on a 20 degree slope with mu = 0.2 < tan 20 slides with acceleration
    g (sin 20 - mu cos 20) = 1.5115 m/s^2: quadratic least-squares fit of its downhill position
    against time over the samples after ``fit_after`` s; tolerance 1e-3 relative."""
    run, n, down = _slope_run(response, substeps, mu, angle_deg, seconds)
    t, bq = run.t, run.body_q[:, 0]
    s = (bq[:, :3] - bq[0, :3]) @ down
    keep = t >= fit_after - 1e-12
    c2, c1, c0 = np.polyfit(t[keep], s[keep], 2)
    accel = 2.0 * c2
    a = math.radians(angle_deg)
    expected = GRAVITY * (math.sin(a) - mu * math.cos(a))
    fit = np.polyval([c2, c1, c0], t[keep])
    return [_record("slope_sliding", response, substeps, "acceleration along the slope [m/s^2]", accel,
                    expected_value=expected, tolerance=1e-3, mode="rel",
                    expected=f"g(sin {angle_deg:g} - mu cos {angle_deg:g}) = {expected:.4f}",
                    reference="Coulomb sliding friction on an incline: a = g (sin a - mu cos a); semi-implicit "
                              "Euler under a constant force follows a parabola with exactly this quadratic "
                              "coefficient",
                    variant=f"mu={mu:g}, {seconds:g} s, fit t >= {fit_after:g} s",
                    fit_residual=float(np.abs(fit - s[keep]).max()),
                    max_rotation=float(rotation_angle(bq[:, 3:], bq[0, 3:]).max()),
                    max_off_slope=float(np.abs((bq[:, :3] - bq[0, :3]) @ np.cross(n, down)).max()),
                    failsafe=run.failsafe_count)]


# --------------------------------------------------------------------------------------------
# 6-7: resting contact, stacks
# --------------------------------------------------------------------------------------------


def _rest_records(name: str, run: Run, response: str, substeps: int, seconds: float, settle: float) -> list[Record]:
    t, bq, bqd = run.t, run.body_q[:, 0], run.body_qd[:, 0]
    late = t >= settle - 1e-12
    speed = np.linalg.norm(bqd[:, 3:], axis=-1)
    omega = np.linalg.norm(bqd[:, :3], axis=-1)
    drift = _horizontal_drift(bq[:, :3])
    yaw = np.abs(twist_angle(bq[:, 3:], bq[0, 3:]))
    ref = "a box placed at rest, flat, at the contact separation stays at rest (no motion, no rotation)"
    common = dict(variant=f"{seconds:g} s", reference=ref, failsafe=run.failsafe_count,
                  max_omega_after_settle=float(omega[late].max()),
                  max_vertical_motion=float(np.abs(bq[:, 2] - bq[0, 2]).max()), final_speed=float(speed[-1]))
    return [
        _record(name, response, substeps, f"max speed after {settle:g} s [m/s]", speed[late].max(), tolerance=1e-6,
                expected="0", **common),
        _record(name, response, substeps, "max horizontal drift [m]", drift.max(), tolerance=1e-6, expected="0",
                **common),
        _record(name, response, substeps, "max abs yaw [rad]", yaw.max(), tolerance=1e-6, expected="0", **common),
    ]


def check_rest_plane(response: str = "replayed", substeps: int = 8, *, seconds: float = 10.0,
                     settle: float = 1.0) -> list[Record]:
    """A box (half 0.1 m, mu 0.5) at rest on the ground plane, its bottom at the separation:
    speed after ``settle`` s <= 1e-6 m/s, horizontal drift <= 1e-6 m, |yaw| <= 1e-6 rad."""
    b = scene_builder()
    add_box(b, BOX_HALF, (0.0, 0.0, BOX_HALF + THICKNESS))
    b.add_ground_plane()
    run = Run(b, response, substeps).run_for(seconds)
    return _rest_records("rest_plane", run, response, substeps, seconds, settle)


def check_rest_box(response: str = "replayed", substeps: int = 8, *, seconds: float = 10.0,
                   settle: float = 1.0) -> list[Record]:
    """A box (half 0.1 m, mu 0.5) at rest on a static box mesh (half 0.2 m at the origin, top
    z = 0.2), its bottom at the separation: the same bounds as :func:`check_rest_plane`."""
    from sim.mesh_io import box_mesh

    b = scene_builder()
    add_box(b, BOX_HALF, (0.0, 0.0, 0.2 + BOX_HALF + THICKNESS))
    b.add_static_mesh(*box_mesh(0.2))
    run = Run(b, response, substeps).run_for(seconds)
    return _rest_records("rest_box", run, response, substeps, seconds, settle)


def check_stack(response: str = "replayed", substeps: int = 8, *, boxes: int = 3,
                seconds: float = 10.0) -> list[Record]:
    """A stack of ``boxes`` boxes (half 0.1 m, mu 0.5) on the ground plane, each at the
    separation above the one below, at rest: it stands; the top box's displacement at the end
    <= 1e-3 m, its speed at the end <= 1e-6 m/s, and no box turns by more than 1e-6 rad (a
    stack can stand while it turns as a whole)."""
    b = scene_builder()
    for k in range(int(boxes)):
        add_box(b, BOX_HALF, (0.0, 0.0, BOX_HALF + THICKNESS + k * (2 * BOX_HALF + THICKNESS)))
    b.add_ground_plane()
    run = Run(b, response, substeps).run_for(seconds)
    bq, bqd = run.body_q, run.body_qd
    top = int(boxes) - 1
    disp = np.linalg.norm(bq[-1, top, :3] - bq[0, top, :3])
    speed = np.linalg.norm(bqd[-1, top, 3:])
    drift = max(_horizontal_drift(bq[:, k, :3]).max() for k in range(int(boxes)))
    tilt = max(rotation_angle(bq[:, k, 3:], bq[0, k, 3:]).max() for k in range(int(boxes)))
    ref = "a stack of aligned boxes at rest is in equilibrium: it stands still"
    common = dict(variant=f"{boxes} boxes, {seconds:g} s", reference=ref, failsafe=run.failsafe_count,
                  max_horizontal_drift_any_box=float(drift),
                  top_final_omega=float(np.linalg.norm(bqd[-1, top, :3])))
    return [
        _record("stack", response, substeps, "top box displacement at the end [m]", disp, tolerance=1e-3,
                expected="0 (stands)", **common),
        _record("stack", response, substeps, "top box speed at the end [m/s]", speed, tolerance=1e-6, expected="0",
                **common),
        _record("stack", response, substeps, "largest rotation of any box [rad]", float(tilt), tolerance=1e-6,
                expected="0", **common),
    ]


# --------------------------------------------------------------------------------------------
# 8-9: impacts in zero gravity
# --------------------------------------------------------------------------------------------


def _impact_run(response: str, substeps: int, restitution: float, gap: float, speed: float, free_target: bool,
                after: float) -> tuple[Run, int]:
    """Box A (half 0.1 m) at ``speed`` along +x, its +x face ``gap`` m from the -x face of box B
    (half 0.1 m at the origin; a static mesh, or a free body when ``free_target``); zero
    gravity, friction 0; run until ``after`` s past the (zero-thickness) impact time."""
    from sim.mesh_io import box_mesh

    b = scene_builder(gravity=(0.0, 0.0, 0.0), restitution=restitution, friction=0.0)
    a = add_box(b, BOX_HALF, (-(2 * BOX_HALF + gap), 0.0, 0.0), velocity=(speed, 0.0, 0.0))
    if free_target:
        add_box(b, BOX_HALF, (0.0, 0.0, 0.0))
    else:
        b.add_static_mesh(*box_mesh(BOX_HALF))
    run = Run(b, response, substeps)
    run.step(int(math.ceil((gap / speed + after) / DT)))
    return run, a


def check_restitution_sweep(response: str = "replayed", substeps: int = 8, *, restitution: float = 0.5,
                            gaps: Sequence[float] = RESTITUTION_GAPS, speed: float = 1.0,
                            after: float = 0.1) -> list[Record]:
    """Zero gravity: a box at 1 m/s towards a static box, face to face, for each initial gap
    (impact at different phases of a substep). The normal velocity read ``after`` s past the
    impact is ``-e`` m/s (relative error 1e-6; for e = 0 the rebound is <= 1e-3 of the impact
    speed); the box never turns (|omega| <= 1e-9 rad/s over the run, the worst gap); the fail-safe
    never fires (summed over the gaps)."""
    e = float(restitution)
    expected = -e * speed
    out, omegas, failsafes = [], {}, {}
    variant = f"e={e:g}"
    for gap in gaps:
        run, a = _impact_run(response, substeps, e, gap, speed, False, after)
        bqd = run.body_qd[:, a]
        vx = float(bqd[-1, 3])
        omegas[gap] = float(np.linalg.norm(bqd[:, :3], axis=-1).max())
        failsafes[gap] = run.failsafe_count
        phase = (gap / speed) / (DT / substeps)
        phase -= math.floor(phase + 1e-9)
        info = dict(variant=f"{variant}, gap={gap:g} m", gap=gap, impact_time=gap / speed,
                    substep_phase=round(phase, 6), failsafe=run.failsafe_count, max_omega=omegas[gap],
                    post_velocity=bqd[-1, 3:], read_at=float(run.t[-1]))
        if e == 0.0:
            out.append(_record("restitution_sweep", response, substeps, "post-impact normal velocity [m/s]", vx,
                               expected_value=0.0, tolerance=1e-3 * speed, expected="0 (perfectly inelastic)",
                               reference="Newton's restitution law v+ = -e v-; e = 0: rebound <= 1e-3 of the "
                                         "impact speed", **info))
        else:
            out.append(_record("restitution_sweep", response, substeps, "post-impact normal velocity [m/s]", vx,
                               expected_value=expected, tolerance=1e-6, mode="rel", expected=f"-e v = {expected:g}",
                               reference="Newton's restitution law v+ = -e v- (static target, face-to-face, "
                                         "frictionless)", **info))
    worst = max(omegas, key=omegas.get)
    out.append(_record("restitution_sweep", response, substeps, "max omega norm (worst gap) [rad/s]", omegas[worst],
                       tolerance=1e-9, expected="0", variant=variant,
                       reference="symmetry: a face-to-face impact gives a normal impulse through the centre of mass",
                       worst_gap=worst, per_gap=omegas))
    out.append(_record("restitution_sweep", response, substeps, "fail-safe substeps (all gaps)",
                       sum(failsafes.values()), tolerance=0.0, expected="0", variant=variant,
                       reference="an isolated two-body impact needs no rigid impact zone", per_gap=failsafes))
    return out


def check_head_on(response: str = "replayed", substeps: int = 8, *, gap: float = 0.05, speed: float = 1.0,
                  after: float = 0.1) -> list[Record]:
    """Zero gravity, e = 1: box A at 1 m/s hits box B (equal mass) at rest, face to face: the
    velocities swap (A: 0, B: 1 m/s; tolerance 1e-6 m/s), linear momentum is conserved to 1e-12
    (relative) and the fail-safe never fires."""
    run, a = _impact_run(response, substeps, 1.0, gap, speed, True, after)
    bqd, bq = run.body_qd, run.body_q
    mass = run.model.body_mass.numpy()
    va, vb = float(bqd[-1, 0, 3]), float(bqd[-1, 1, 3])
    p0 = np.sum(mass[:, None] * bqd[0, :, 3:], axis=0)
    p_err = max(np.linalg.norm(np.sum(mass[:, None] * bqd[k, :, 3:], axis=0) - p0) for k in range(len(bqd)))
    p_err /= np.linalg.norm(p0)
    variant = f"gap={gap:g} m"
    ref = "elastic collision of equal masses: the velocities swap (1D, e = 1)"
    info = dict(variant=variant, failsafe=run.failsafe_count, read_at=float(run.t[-1]),
                max_omega=float(np.linalg.norm(bqd[:, :, :3], axis=-1).max()), final_velocities=bqd[-1, :, 3:],
                final_positions=bq[-1, :, :3])
    return [
        _record("head_on", response, substeps, "A velocity after [m/s]", va, expected_value=0.0, tolerance=1e-6,
                expected="0", reference=ref, **info),
        _record("head_on", response, substeps, "B velocity after [m/s]", vb, expected_value=speed, tolerance=1e-6,
                expected=f"{speed:g}", reference=ref, **info),
        _record("head_on", response, substeps, "max relative momentum error", p_err, tolerance=1e-12, expected="0",
                reference="no external force: total linear momentum is conserved", **info),
        _record("head_on", response, substeps, "fail-safe substeps", run.failsafe_count, tolerance=0.0, expected="0",
                reference="an isolated two-body impact needs no rigid impact zone", **info),
    ]


# --------------------------------------------------------------------------------------------
# 10: torque-free rotation
# --------------------------------------------------------------------------------------------

FREE_HALF = (0.1, 0.2, 0.3)
FREE_OMEGA = (1.0, 5.0, 0.1)


def _crossings(t: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Times of the sign changes of samples ``y(t)`` (linear interpolation)."""
    s = np.flatnonzero(np.sign(y[:-1]) * np.sign(y[1:]) < 0)
    return t[s] - y[s] * (t[s + 1] - t[s]) / (y[s + 1] - y[s])


def euler_reference(inertia, omega0, seconds: float):
    """Body-frame Euler equations of a torque-free body with principal moments ``inertia`` by
    scipy's DOP853 (rtol 1e-12, atol 1e-14): the times at which the intermediate-axis component
    of the angular velocity changes sign, in [0, seconds]."""
    from scipy.integrate import solve_ivp

    i1, i2, i3 = (float(x) for x in inertia)

    def f(_t, w):
        return [(i2 - i3) * w[1] * w[2] / i1, (i3 - i1) * w[2] * w[0] / i2, (i1 - i2) * w[0] * w[1] / i3]

    mid = int(np.argsort(inertia)[1])

    def event(_t, w):
        return w[mid]

    sol = solve_ivp(f, (0.0, seconds), list(omega0), method="DOP853", rtol=1e-12, atol=1e-14, events=event)
    return sol.t_events[0], mid


def check_free_rotation(response: str = "replayed", substeps: int = 8, *, seconds: float = 5.0) -> list[Record]:
    """Zero gravity, no contact: a box of half extents 0.1 x 0.2 x 0.3 m spun at omega0 =
    (1, 5, 0.1) rad/s (mostly about its intermediate axis y: the Dzhanibekov flip). Relative
    energy drift <= 1e-3, relative angular-momentum drift <= 1e-9, and the interval between
    flips (sign changes of the body-frame omega_y) within 1 % of scipy's DOP853 solution of
    Euler's equations (rtol 1e-12)."""
    b = scene_builder(gravity=(0.0, 0.0, 0.0))
    add_box(b, FREE_HALF, (0.0, 0.0, 0.0), angular_velocity=FREE_OMEGA)
    run = Run(b, response, substeps).run_for(seconds)
    t, bq, bqd = run.t, run.body_q[:, 0], run.body_qd[:, 0]
    inertia_b = run.model.body_inertia.numpy()[0]
    R = _rot_matrix(bq[:, 3:])
    w = bqd[:, :3]
    Iw = np.einsum("nij,jk,nlk->nil", R, inertia_b, R)
    L = np.einsum("nij,nj->ni", Iw, w)
    E = 0.5 * np.einsum("ni,ni->n", w, L)
    e_drift = float(np.abs(E - E[0]).max() / E[0])
    l_drift = float(np.linalg.norm(L - L[0], axis=-1).max() / np.linalg.norm(L[0]))
    w_body = np.einsum("nji,nj->ni", R, w)
    principal = np.diag(inertia_b)
    ref_times, mid = euler_reference(principal, FREE_OMEGA, seconds + 5 * DT)
    sim_times = _crossings(t, w_body[:, mid])
    ref_interval = float(np.mean(np.diff(ref_times))) if len(ref_times) >= 2 else math.nan
    sim_interval = float(np.mean(np.diff(sim_times))) if len(sim_times) >= 2 else math.nan
    if not math.isfinite(ref_interval):  # too short for two flips: the full reference interval
        more, _ = euler_reference(principal, FREE_OMEGA, 20.0)
        ref_interval = float(np.mean(np.diff(more[:3])))
    variant = f"{seconds:g} s"
    info = dict(variant=variant, failsafe=run.failsafe_count, sim_flip_times=sim_times, ref_flip_times=ref_times,
                inertia_diagonal=principal, off_diagonal_inertia=float(np.abs(inertia_b - np.diag(principal)).max()))
    first_sim = sim_times[0] if len(sim_times) else math.nan
    first = (_record("free_rotation", response, substeps, "first flip time [s]", first_sim,
                     expected_value=ref_times[0], tolerance=1e-2, mode="rel",
                     expected=f"{ref_times[0]:.5f} (DOP853)",
                     reference="Euler's equations, scipy solve_ivp DOP853 rtol 1e-12 atol 1e-14", **info)
             if len(ref_times) else None)
    out = [
        _record("free_rotation", response, substeps, "max relative energy drift", e_drift, tolerance=1e-3,
                expected="0", reference="torque-free motion conserves the kinetic energy 1/2 w.I_w w", **info),
        _record("free_rotation", response, substeps, "max relative angular momentum drift", l_drift, tolerance=1e-9,
                expected="0", reference="torque-free motion conserves the world angular momentum I_w w", **info),
        _record("free_rotation", response, substeps, "flip interval [s]", sim_interval, expected_value=ref_interval,
                tolerance=1e-2, mode="rel", expected=f"{ref_interval:.5f} (DOP853)",
                reference="interval between sign changes of the body-frame omega about the intermediate axis, "
                          "Euler's equations by scipy solve_ivp DOP853 rtol 1e-12 atol 1e-14", **info),
    ]
    if first is not None:
        out.append(first)
    return out


# --------------------------------------------------------------------------------------------
# 11-13: cloth
# --------------------------------------------------------------------------------------------

CLOTH = dict(density=0.2, stretch_stiffness=20.0, shear_stiffness=10.0, bend_stiffness=1.0, damping=0.01)
"""The cloth_drop scene's cloth parameters (0.05 m cells)."""


def _cloth_flat_box_builder(cells: int, size: float, height: float, box_half: float, restitution: float):
    from sim.mesh_io import box_mesh

    b = scene_builder(friction=0.3, restitution=restitution)
    cell = size / cells
    b.add_cloth_grid((-size / 2, -size / 2, height), None, cells, cells, cell, cell, **CLOTH)
    b.add_static_mesh(*box_mesh(box_half))
    return b


def check_cloth_flat_box(response: str = "replayed", substeps: int = 8, *, steps: int = 20, count: int = 9,
                         eps: float = 1e-9, cells: int = 8, height: float = 0.55,
                         restitution: float = 0.5) -> list[Record]:
    """An 8 x 8-cell cloth (0.4 m square, centred, flat at z = ``height``) falls onto the top face
    of a static box (half 0.25 m at the origin: top z = 0.25; restitution 0.5, mu 0.3); loss = the
    particles' mean height after ``steps`` steps (at 0.55 m the impact falls in step 15 and the
    loss is read on the rebound: with e = 0 the cloth would stop at the contact height whatever
    its velocity, a constant loss). With every particle's initial vertical velocity shifted by
    ``count`` values of e in [-eps, eps] the loss must be a straight line in e: the largest
    residual from the least-squares line <= 1e-12 m (a contact decision or rounding that jumps
    shows as a residual)."""
    es = np.linspace(-eps, eps, int(count))
    losses = []
    failsafe = 0
    for e in es:
        b = _cloth_flat_box_builder(cells, 0.4, height, 0.25, restitution)
        qd = np.zeros((b.particle_count, 3))
        qd[:, 2] = e
        run = Run(b, response, substeps, particle_qd=qd).step(steps)
        losses.append(float(run.particle_q[-1][:, 2].mean()))
        failsafe += run.failsafe_count
    losses = np.array(losses)
    slope, icpt = np.polyfit(es, losses, 1)
    resid = float(np.abs(losses - (slope * es + icpt)).max())
    return [_record("cloth_flat_box", response, substeps, "max residual from a line [m]", resid, tolerance=1e-12,
                    expected="0 (loss linear in e)",
                    reference="the loss is smooth in the initial velocity: over abs(e) <= 1e-9 m/s it is linear to "
                              "rounding (a first-order Taylor expansion; the quadratic term is ~1e-18)",
                    variant=f"{count} x e in [-{eps:g}, {eps:g}] m/s, e={restitution:g}, {steps} steps",
                    losses=losses, slope=slope, failsafe=failsafe)]


def _hanging_builder(cfg: dict):
    """The cloth in the x-y plane (no rotation: every z is exactly 0) with gravity along -y, pinned
    at its two top corners (y = 1 m): the forces have no z component, so the motion stays exactly
    planar (a cloth rotated into the x-z plane gets z ~ 1e-17 from the quaternion's rounding, and
    its compressed bottom edge buckled out of the plane from it and swung about the pins, a mode
    the spring damping does not reach)."""
    b = scene_builder(gravity=(0.0, -GRAVITY, 0.0))
    n, size = int(cfg["cells"]), float(cfg["size"])
    cell = size / n
    top_left, top_right = n * (n + 1), n * (n + 1) + n
    b.add_cloth_grid((-size / 2, 1.0 - size, 0.0), None, n, n, cell, cell,
                     density=cfg["density"], stretch_stiffness=cfg["stretch_stiffness"],
                     shear_stiffness=cfg["shear_stiffness"], bend_stiffness=cfg["bend_stiffness"],
                     damping=cfg["damping"], pinned=[top_left, top_right])
    return b


def spring_equilibrium(model, x_start: np.ndarray, axes: Sequence[int] = (0, 1, 2)) -> tuple[np.ndarray, float]:
    """The static equilibrium of the model's springs under gravity near ``x_start`` (P, 3): the
    minimum of ``sum 1/2 k (|xi - xj| - L)^2 - sum m g.x`` over the free particles' coordinates
    ``axes`` (the others and the pinned particles fixed) by Newton's method (scipy trust-exact
    with the exact Hessian). Returns the positions and the largest force residual [N] (on the
    coordinates ``axes``)."""
    from scipy.optimize import minimize

    axes = np.asarray(axes, dtype=np.int64)
    na = len(axes)
    idx = model.spring_indices.numpy().reshape(-1, 2)
    rest = model.spring_rest_length.numpy()
    k = model.spring_stiffness.numpy()
    mass = model.particle_mass.numpy()
    g = np.asarray(model.gravity, dtype=np.float64)
    free = np.flatnonzero(model.particle_inv_mass.numpy() > 0)
    pos = np.array(x_start, dtype=np.float64)
    slot = -np.ones(len(pos), dtype=np.int64)
    slot[free] = np.arange(len(free))

    def unpack(z):
        x = pos.copy()
        x[np.ix_(free, axes)] = z.reshape(-1, na)
        return x

    def energy(z):
        x = unpack(z)
        d = x[idx[:, 1]] - x[idx[:, 0]]
        l = np.linalg.norm(d, axis=1)
        return 0.5 * np.sum(k * (l - rest) ** 2) - np.sum(mass * (x @ g))

    def forces(x):
        d = x[idx[:, 1]] - x[idx[:, 0]]
        l = np.linalg.norm(d, axis=1)
        f = (k * (l - rest) / l)[:, None] * d  # on i towards j
        out = np.zeros_like(x)
        np.add.at(out, idx[:, 0], f)
        np.add.at(out, idx[:, 1], -f)
        return out + mass[:, None] * g

    def grad(z):
        return -forces(unpack(z))[np.ix_(free, axes)].reshape(-1)

    def hess(z):
        x = unpack(z)
        d = x[idx[:, 1]] - x[idx[:, 0]]
        l = np.linalg.norm(d, axis=1)
        u = d / l[:, None]
        eye = np.eye(3)
        blocks = k[:, None, None] * ((1.0 - rest / l)[:, None, None] * eye + (rest / l)[:, None, None]
                                     * np.einsum("si,sj->sij", u, u))
        blocks = blocks[:, axes][:, :, axes]
        H = np.zeros((na * len(free), na * len(free)))
        for (i, j), B in zip(idx, blocks):
            si, sj = slot[i], slot[j]
            if si >= 0:
                H[na * si:na * si + na, na * si:na * si + na] += B
            if sj >= 0:
                H[na * sj:na * sj + na, na * sj:na * sj + na] += B
            if si >= 0 and sj >= 0:
                H[na * si:na * si + na, na * sj:na * sj + na] -= B
                H[na * sj:na * sj + na, na * si:na * si + na] -= B
        return H

    z = pos[np.ix_(free, axes)].reshape(-1)
    res = minimize(energy, z, jac=grad, hess=hess, method="trust-exact", options={"gtol": 1e-12, "maxiter": 500})
    z = res.x
    for _ in range(3):  # polish: plain Newton steps at the minimum
        z = z - np.linalg.solve(hess(z), grad(z))
    x = unpack(z)
    return x, float(np.abs(forces(x)[np.ix_(free, axes)]).max())


HANG = dict(cells=4, size=0.4, density=2.0, stretch_stiffness=100.0, shear_stiffness=100.0 / 3,
            bend_stiffness=100.0 / 30, damping=0.3)
"""The hanging cloth: 4 x 4 cells, 0.4 m square; a heavy cloth (2 kg/m^2) with springs of 100,
33.3 and 3.33 N/m and damping 0.3 N s/m, so that it settles within 6 s and is stable at 4
substeps (finer or lighter cloths kept swinging for tens of seconds: spring damping reaches the
lowest mode only weakly, and explicit damping is bounded by the light corner particles)."""


def check_cloth_hanging(response: str = "replayed", substeps: int = 8, *, seconds: float = 10.0,
                        cloth: dict | None = None) -> list[Record]:
    """A cloth (:data:`HANG`) hanging from its two pinned top corners in its own plane (the x-y
    plane, gravity along -y: the motion stays exactly planar), released flat and unstretched at
    rest: after ``seconds`` its sag (drop of the free particles' centroid) equals that of the
    planar static equilibrium of the same springs under gravity (the limit of many substeps and
    a long settle, found directly by Newton's method on the spring energy over the in-plane
    coordinates); tolerance 1e-3 relative."""
    cfg = dict(HANG, **(cloth or {}))
    b = _hanging_builder(cfg)
    run = Run(b, response, substeps).run_for(seconds)
    q = run.particle_q
    free = np.flatnonzero(run.model.particle_inv_mass.numpy() > 0)
    x_eq, residual = spring_equilibrium(run.model, q[-1], axes=(0, 1))
    y0 = q[0][free, 1].mean()
    sag = float(y0 - q[-1][free, 1].mean())
    sag_ref = float(y0 - x_eq[free, 1].mean())
    sags = y0 - q[:, free, 1].mean(axis=1)
    last = run.t >= run.t[-1] - 1.0 - 1e-12
    return [_record("cloth_hanging", response, substeps, "sag of the centroid [m]", sag, expected_value=sag_ref,
                    tolerance=1e-3, mode="rel", expected=f"{sag_ref:.6f} (static equilibrium)",
                    reference="planar static equilibrium of the same spring network under gravity (pinned corners "
                              "fixed), Newton's method on the spring + gravity energy (force residual < 1e-9 N): the "
                              "limit of many substeps and a long settle",
                    variant=f"{cfg['cells']}x{cfg['cells']}, damping {cfg['damping']:g}, {seconds:g} s",
                    equilibrium_force_residual=residual, sag_range_last_second=float(np.ptp(sags[last])),
                    max_particle_distance_to_equilibrium=float(np.linalg.norm(q[-1] - x_eq, axis=1).max()),
                    final_max_speed=float(np.linalg.norm(run.particle_qd[-1], axis=1).max()),
                    max_out_of_plane=float(np.abs(q[:, :, 2]).max()), failsafe=run.failsafe_count)]


SPHERE = dict(cells=8, size=0.4, radius=0.15, subdivisions=2, drop=0.02, density=1.0, stretch_stiffness=20.0,
              shear_stiffness=10.0, bend_stiffness=1.0, damping=0.03, drag=1.0)
"""The cloth on the sphere: 8 x 8 cells, 0.4 m, centred ``drop`` m above an icosphere of radius
0.15 m (2 subdivisions) at the origin; 1 kg/m^2, springs 20 / 10 / 1 N/m, damping 0.03 N s/m
(heavier and more damped than the cloth_drop scene's cloth so that it settles; more damping
is unstable at 4 substeps at the light corner particles), air drag 1/s
(:attr:`sim.builder.ModelBuilder.particle_drag`: the spring damping acts along the springs
only, and the draped corners, swinging about the folds, would swing on for minutes)."""


def check_cloth_on_sphere(response: str = "replayed", substeps: int = 8, *, seconds: float = 10.0,
                          window: float = 1.0, friction: float = 0.5) -> list[Record]:
    """A cloth (:data:`SPHERE`) dropped centred onto a static icosphere (mu 0.5) drapes over it
    and comes to rest: its centre particle, on top of the sphere, moves <= 1e-6 m horizontally
    over the last ``window`` s (creep) of ``seconds`` (10 s in both modes)."""
    from sim.mesh_io import icosphere

    cfg = SPHERE
    n, size = int(cfg["cells"]), float(cfg["size"])
    cell = size / n
    b = scene_builder(friction=friction)
    b.particle_drag = cfg["drag"]
    material = {k: cfg[k] for k in ("density", "stretch_stiffness", "shear_stiffness", "bend_stiffness", "damping")}
    b.add_cloth_grid((-size / 2, -size / 2, cfg["radius"] + cfg["drop"]), None, n, n, cell, cell, **material)
    b.add_static_mesh(*icosphere(cfg["radius"], cfg["subdivisions"]))
    run = Run(b, response, substeps).run_for(seconds)
    centre = (n // 2) * (n + 1) + n // 2
    t, q = run.t, run.particle_q
    k0 = int(np.searchsorted(t, t[-1] - window - 1e-12))
    creep = float(np.linalg.norm(q[-1, centre, :2] - q[k0, centre, :2]))
    centroid = q.mean(axis=1)
    speeds = np.linalg.norm(run.particle_qd, axis=2).max(axis=1)
    return [_record("cloth_on_sphere", response, substeps,
                    f"centre particle horizontal creep over the last {window:g} s [m]", creep, tolerance=1e-6,
                    expected="0 (at rest)",
                    reference="a symmetric cloth draped over a sphere with friction comes to rest (static "
                              "equilibrium); its centre, on top of the sphere, does not creep",
                    variant=f"{n}x{n}, mu={friction:g}, {seconds:g} s",
                    creep_3d=float(np.linalg.norm(q[-1, centre] - q[k0, centre])),
                    centroid_motion_last_window=float(np.linalg.norm(centroid[-1] - centroid[k0])),
                    centre_height=float(q[-1, centre, 2]), centre_horizontal=q[-1, centre, :2],
                    max_speed_last_window=float(speeds[k0:].max()), failsafe=run.failsafe_count)]


# --------------------------------------------------------------------------------------------
# 14-15: sliding friction, bounce
# --------------------------------------------------------------------------------------------


def check_sliding_friction(response: str = "replayed", substeps: int = 8, *, mu: float = 0.3, speed: float = 2.0,
                           seconds: float = 1.2) -> list[Record]:
    """A box (half 0.1 m) on the ground plane at the separation, sliding at 2 m/s along x with
    mu = 0.3: it stops after v^2 / (2 mu g) = 0.6797 m (within 0.2 %)."""
    b = scene_builder(friction=mu)
    add_box(b, BOX_HALF, (0.0, 0.0, BOX_HALF + THICKNESS), velocity=(speed, 0.0, 0.0))
    b.add_ground_plane()
    run = Run(b, response, substeps).run_for(seconds)
    bq, bqd = run.body_q[:, 0], run.body_qd[:, 0]
    dist = float(bq[-1, 0] - bq[0, 0])
    expected = speed * speed / (2.0 * mu * GRAVITY)
    moving = np.flatnonzero(np.abs(bqd[:, 3]) > 1e-9)
    stop_time = float(run.t[moving[-1] + 1]) if len(moving) and moving[-1] + 1 < len(run.t) else math.nan
    return [_record("sliding_friction", response, substeps, "stopping distance [m]", dist, expected_value=expected,
                    tolerance=2e-3, mode="rel", expected=f"v^2/(2 mu g) = {expected:.5f}",
                    reference="Coulomb friction: constant deceleration mu g until the box stops",
                    variant=f"mu={mu:g}, v={speed:g} m/s, {seconds:g} s",
                    final_speed=float(np.linalg.norm(bqd[-1, 3:])), stop_time=stop_time,
                    expected_stop_time=speed / (mu * GRAVITY),
                    max_rotation=float(rotation_angle(bq[:, 3:], bq[0, 3:]).max()),
                    max_lateral=float(np.abs(bq[:, 1] - bq[0, 1]).max()), failsafe=run.failsafe_count)]


def _apex_ratio(t: np.ndarray, z: np.ndarray, vz: np.ndarray, contact_height: float):
    """(apex ratio, apex before, apex after, fitted gravity before, after) of the first bounce of
    heights ``z`` [m] sampled at ``t`` [s] (``vz`` the vertical velocities), both apexes above
    ``contact_height``: the top of the parabola fitted through each flight's samples (a
    semi-implicit Euler flight lies exactly on one)."""
    bounce = int(np.flatnonzero(vz > 0)[0])  # first sample moving up: the bounce was in the step before
    # second bounce: samples after it must be excluded
    later = np.flatnonzero((np.arange(len(vz)) > bounce) & (vz > 0) & (np.roll(vz, 1) < 0))
    end = int(later[0]) - 1 if len(later) else len(vz)

    def apex(tt, zz):
        c2, c1, c0 = np.polyfit(tt, zz, 2)
        return c0 - c1 * c1 / (4.0 * c2), 2.0 * c2

    a0, g0 = apex(t[:bounce - 1], z[:bounce - 1])
    a1, g1 = apex(t[bounce:end], z[bounce:end])
    return (a1 - contact_height) / (a0 - contact_height), a0, a1, g0, g1


BALL_RADIUS = 0.05


def check_ball_bounce(response: str = "replayed", substeps: int = 8, *, restitution: float = 0.5,
                      height: float = 1.0) -> list[Record]:
    """A sphere body (radius 0.05 m, 1 kg) dropped from ``height`` m above its contact height
    onto the ground plane with restitution e: the apex ratio is e^2 (the particles' plane law,
    :func:`kernels.integrate.plane_rebound`; tolerance 1e-3 relative)."""
    b = scene_builder(restitution=restitution, friction=0.0)
    b.add_sphere(BALL_RADIUS, mass=1.0, pos=(0.0, 0.0, BALL_RADIUS + THICKNESS + height))
    b.add_ground_plane()
    fall = math.sqrt(2.0 * height / GRAVITY)
    up = restitution * math.sqrt(2.0 * GRAVITY * height) / GRAVITY
    run = Run(b, response, substeps).run_for(fall + 1.8 * up)
    ratio, a0, a1, _, _ = _apex_ratio(run.t, run.body_q[:, 0, 2], run.body_qd[:, 0, 5], BALL_RADIUS + THICKNESS)
    e2 = restitution * restitution
    return [_record("ball_bounce", response, substeps, "apex ratio", ratio, expected_value=e2, tolerance=1e-3,
                    mode="rel", expected=f"e^2 = {e2:g}", reference="Newton's restitution law (as sphere_bounce)",
                    variant=f"sphere body, e={restitution:g}", apex_before=a0, apex_after=a1)]


def check_ball_roll(response: str = "replayed", substeps: int = 8, *, mu: float = 0.3, speed: float = 1.0,
                    seconds: float = 1.0) -> list[Record]:
    """A sphere body sliding at ``speed`` without spin on the ground plane (friction ``mu``, no
    bounce): friction spins it up until it rolls at 5/7 of its speed (the angular momentum about
    the contact point is kept), within ``2 v / (7 mu g)`` = 0.1 s, and then rolls on."""
    b = scene_builder(restitution=0.0, friction=mu)
    b.add_sphere(BALL_RADIUS, mass=1.0, pos=(0.0, 0.0, BALL_RADIUS + THICKNESS), velocity=(speed, 0.0, 0.0))
    b.add_ground_plane()
    run = Run(b, response, substeps).run_for(seconds)
    qd = run.body_qd[-1, 0]
    return [_record("ball_roll", response, substeps, "final speed / initial", qd[3] / speed, expected_value=5.0 / 7.0,
                    tolerance=1e-9, expected="5/7", reference="sliding to rolling: L about the contact point kept",
                    variant=f"mu={mu:g}"),
            _record("ball_roll", response, substeps, "slip speed w r - v [m/s]", qd[1] * BALL_RADIUS - qd[3],
                    tolerance=1e-9, expected="0 (rolling)", reference="rolling without slipping",
                    variant=f"mu={mu:g}")]


def check_ball_head_on(response: str = "replayed", substeps: int = 8) -> list[Record]:
    """Two equal spheres, no gravity, an elastic head-on impact: the velocities swap."""
    b = scene_builder(gravity=(0.0, 0.0, 0.0), restitution=1.0, friction=0.0, thickness=0.0)
    b.add_sphere(BALL_RADIUS, mass=1.0, pos=(0.0, 0.0, 0.0), velocity=(1.0, 0.0, 0.0))
    b.add_sphere(BALL_RADIUS, mass=1.0, pos=(0.3, 0.0, 0.0))
    run = Run(b, response, substeps).run_for(0.5)
    qd = run.body_qd[-1]
    return [_record("ball_head_on", response, substeps, "|v1| + |v2 - (1, 0, 0)| [m/s]",
                    np.linalg.norm(qd[0]) + np.linalg.norm(qd[1, 3:] - (1.0, 0.0, 0.0)), tolerance=1e-12,
                    expected="0 (swapped)", reference="equal masses, e = 1: exchange of velocities")]


def check_sphere_bounce(response: str = "replayed", substeps: int = 8, *, restitution: float = 0.5,
                        height: float = 1.0) -> list[Record]:
    """A particle (1 kg) dropped from ``height`` m onto the ground plane with restitution e: the
    apex after the first bounce over the drop height, both measured above the contact height
    (the separation), is e^2 (tolerance 1e-3 relative). Each apex is the top of the parabola
    fitted through the step samples of that flight (a semi-implicit Euler flight lies exactly on
    one)."""
    b = scene_builder(restitution=restitution)
    b.add_particle((0.0, 0.0, height), mass=1.0)
    b.add_ground_plane()
    fall = math.sqrt(2.0 * height / GRAVITY)
    up = restitution * math.sqrt(2.0 * GRAVITY * height) / GRAVITY
    run = Run(b, response, substeps).run_for(fall + 1.8 * up)
    sep = run.integrator.plane_separation()
    ratio, a0, a1, g0, g1 = _apex_ratio(run.t, run.particle_q[:, 0, 2], run.particle_qd[:, 0, 2], sep)
    e2 = restitution * restitution
    return [_record("sphere_bounce", response, substeps, "apex ratio", ratio, expected_value=e2, tolerance=1e-3,
                    mode="rel", expected=f"e^2 = {e2:g}",
                    reference="Newton's restitution law: rebound speed e v, so the apex height scales by e^2",
                    variant=f"particle, e={restitution:g}, h={height:g} m", apex_before=a0, apex_after=a1,
                    separation=sep, fitted_gravity=(g0, g1), failsafe=run.failsafe_count)]


# --------------------------------------------------------------------------------------------
# the suite
# --------------------------------------------------------------------------------------------


@dataclass
class Check:
    """A check of the suite: its function and the keyword settings of each variant, per mode."""

    name: str
    function: Callable[..., list[Record]]
    full: list[dict]
    quick: list[dict] | None = None  # None: the full variants

    def variants(self, quick: bool) -> list[dict]:
        return self.quick if quick and self.quick is not None else self.full


CHECKS: dict[str, Check] = {c.name: c for c in [
    Check("flat_drop_plane", check_flat_drop_plane, [dict(friction=0.0), dict(friction=0.3)]),
    Check("flat_drop_static_box", check_flat_drop_static_box, [{}]),
    Check("flat_drop_rigid_box", check_flat_drop_rigid_box, [{}]),
    Check("slope_static", check_slope_static, [dict(mu=0.5), dict(mu=1.0)]),
    Check("slope_sliding", check_slope_sliding, [{}]),
    Check("rest_plane", check_rest_plane, [dict(seconds=10.0)], [dict(seconds=3.0)]),
    Check("rest_box", check_rest_box, [dict(seconds=10.0)], [dict(seconds=3.0)]),
    Check("stack", check_stack, [dict(boxes=3, seconds=10.0), dict(boxes=5, seconds=10.0)],
          [dict(boxes=3, seconds=5.0), dict(boxes=5, seconds=5.0)]),
    Check("restitution_sweep", check_restitution_sweep, [dict(restitution=e) for e in (0.0, 0.5, 1.0)]),
    Check("head_on", check_head_on, [dict(gap=0.05), dict(gap=0.0505)]),
    Check("free_rotation", check_free_rotation, [dict(seconds=5.0), dict(seconds=50.0)], [dict(seconds=5.0)]),
    Check("cloth_flat_box", check_cloth_flat_box, [{}]),
    Check("cloth_hanging", check_cloth_hanging, [dict(seconds=10.0)], [dict(seconds=6.0)]),
    Check("cloth_on_sphere", check_cloth_on_sphere, [dict(seconds=10.0)], [dict(seconds=10.0)]),
    Check("sliding_friction", check_sliding_friction, [{}]),
    Check("sphere_bounce", check_sphere_bounce, [{}]),
    Check("ball_bounce", check_ball_bounce, [{}]),
    Check("ball_roll", check_ball_roll, [{}]),
    Check("ball_head_on", check_ball_head_on, [{}]),
]}
"""The checks by name, in the suite's order."""


def _failed_record(name: str, response: str, substeps: int, kwargs: dict, exc: BaseException) -> Record:
    return Record(name=name, response=response, substeps=int(substeps), quantity="(check raised)",
                  expected="runs", expected_value=math.nan, measured=math.nan, tolerance=math.nan, passed=False,
                  reference="", variant=", ".join(f"{k}={v}" for k, v in kwargs.items()),
                  details={"error": f"{type(exc).__name__}: {exc}"})


def run_suite(quick: bool = False, only: Sequence[str] | None = None, responses: Sequence[str] = tuple(RESPONSES),
              substeps: Sequence[int] | None = None, log=sys.stderr) -> list[Record]:
    """Runs the checks ``only`` (default all) for every response and substep count (default
    :data:`SUBSTEPS_QUICK` with ``quick``, else :data:`SUBSTEPS_FULL`); a check that raises
    gives one failed record naming the error. One progress line per check run on ``log``."""
    names = list(CHECKS) if only is None else list(only)
    bad = [n for n in names if n not in CHECKS]
    if bad:
        raise ValueError(f"unknown check(s) {bad}; choose from {', '.join(CHECKS)}")
    counts = tuple(substeps) if substeps is not None else (SUBSTEPS_QUICK if quick else SUBSTEPS_FULL)
    records: list[Record] = []
    for name in names:
        check = CHECKS[name]
        for kwargs in check.variants(quick):
            for response in responses:
                for n in counts:
                    t0 = time.perf_counter()
                    try:
                        rows = check.function(response=response, substeps=n, **kwargs)
                    except Exception as exc:  # one broken check must not hide the others
                        rows = [_failed_record(name, response, n, kwargs, exc)]
                    records.extend(rows)
                    if log is not None:
                        ok = sum(r.passed for r in rows)
                        state = "PASS" if ok == len(rows) else "FAIL"
                        variant = rows[0].variant.split(", gap=")[0] if rows else ""
                        print(f"[physics] {name} [{variant}] {response} x{n}: {ok}/{len(rows)} passed, {state} "
                              f"({time.perf_counter() - t0:.1f} s)", file=log, flush=True)
    return records


def _cell(value: float) -> str:
    if isinstance(value, float) and math.isfinite(value) and value != 0.0 and (abs(value) < 1e-3 or abs(value) >= 1e5):
        return f"{value:.3e}"
    if isinstance(value, float) and math.isfinite(value):
        return f"{value:.6g}"
    return report.fmt(value)


def _md(text: str) -> str:
    """A table cell's text with its pipes escaped."""
    return str(text).replace("|", "\\|")


def markdown(records: Sequence[Record], quick: bool) -> list[str]:
    """The table (and the references and notes) as markdown lines."""
    lines = [
        f"Mode: {'quick (8 substeps; shorter runs where the variant says so)' if quick else 'full'}; dt = 1/60 s, "
        "thickness 1 mm, boxes of half extent 0.1 m (0.05 m for the dropped box) at 500 kg/m^3, gravity "
        "(0, 0, -9.81) m/s^2 unless the check says otherwise. Responses: gauss_seidel = "
        "ImpulseCollisionHandler(differentiable=False), replayed = differentiable=True (the default, and what "
        "rollout uses). "
        "Tolerance: absolute, or relative ('rel') to the expected value. The tolerances are targets; "
        "a FAIL is a finding about the simulator.",
        "",
        f"**{sum(r.passed for r in records)} of {len(records)} rows pass.**",
        "",
    ]
    rows = []
    for r in records:
        tol = _cell(r.tolerance) + (" rel" if r.mode == "rel" else "")
        rows.append([_md(r.label), r.response, r.substeps, _md(r.expected), _cell(r.measured), tol,
                     "PASS" if r.passed else "FAIL"])
    lines += report.table(["check", "response", "substeps", "reference/expected", "measured", "tolerance", "result"],
                          rows)
    lines += ["", "## References", ""]
    seen = {}
    for r in records:
        key = (r.name, r.reference)
        if r.reference and key not in seen:
            seen[key] = True
            lines.append(f"* `{r.name}`: {r.reference}")
    errors = [r for r in records if "error" in r.details]
    if errors:
        lines += ["", "## Checks that raised", ""]
        lines += [f"* `{r.name}` [{r.variant}] {r.response} x{r.substeps}: {r.details['error']}" for r in errors]
    return lines


def main(argv=None) -> list[Record]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="8 substeps only and shorter runs (minutes)")
    parser.add_argument("--only", default=None, help=f"comma-separated checks (from {', '.join(CHECKS)})")
    parser.add_argument("--out-dir", default=report.RESULTS, help="folder of physics.md / physics.json "
                                                                  "(default %(default)s)")
    parser.add_argument("--responses", default=",".join(RESPONSES),
                        help="comma-separated responses (default %(default)s)")
    parser.add_argument("--substeps", default=None, help="comma-separated substep counts (default: 8 with --quick, "
                                                         "else 4,8,16,32)")
    args = parser.parse_args(argv)
    only = None
    if args.only is not None:
        only = [s.strip() for s in args.only.split(",") if s.strip()]
        bad = [s for s in only if s not in CHECKS]
        if bad or not only:
            parser.error(f"--only: unknown check(s) {bad}; choose from {', '.join(CHECKS)}")
    responses = [s.strip() for s in args.responses.split(",") if s.strip()]
    if not responses or any(r not in RESPONSES for r in responses):
        parser.error(f"--responses: choose from {', '.join(RESPONSES)}")
    substeps = None
    if args.substeps is not None:
        try:
            substeps = [int(s) for s in args.substeps.split(",") if s.strip()]
        except ValueError:
            parser.error("--substeps: comma-separated integers")
        if not substeps or min(substeps) < 1:
            parser.error("--substeps: integers >= 1")
    import warp as wp

    wp.config.quiet = True
    t0 = time.perf_counter()
    records = run_suite(quick=args.quick, only=only, responses=responses, substeps=substeps)
    wall = time.perf_counter() - t0
    settings = {"dt": DT, "thickness": THICKNESS, "density": DENSITY, "box_half": BOX_HALF, "gravity": -GRAVITY,
                "responses": responses, "substeps": list(substeps or (SUBSTEPS_QUICK if args.quick else SUBSTEPS_FULL))}
    data = {"quick": bool(args.quick), "wall_s": wall, "settings": settings, "checks": [r.as_dict() for r in records]}
    lines = markdown(records, args.quick) + ["", f"Wall time {wall:.0f} s."]
    report.write(os.path.join(args.out_dir, "physics"), "Physics validation", lines, data, echo=False)
    print(f"[physics] {sum(r.passed for r in records)}/{len(records)} rows pass; "
          f"{os.path.join(args.out_dir, 'physics')}.md / .json ({wall:.0f} s)", file=sys.stderr, flush=True)
    return records


if __name__ == "__main__":
    main()

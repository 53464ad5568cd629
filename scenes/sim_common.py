"""Shared runner of the simulation scenes (``cloth_drop``, ``rigid_toss``, ``cloth_rigid``).

A simulation scene module defines ``build(builder, args)``, which adds its cloth, bodies and
colliders to a :class:`sim.builder.ModelBuilder` (the builder records the components the scene
needs: ``cloth``, ``rigid``, ``static``), and delegates ``add_arguments`` / ``run`` to this module.

Per step (``dt`` split into ``substeps``): :class:`sim.integrators.semi_implicit.SemiImplicitIntegrator` (or,
with ``--integrator implicit``, :class:`sim.integrators.implicit.ImplicitIntegrator`) with an
:class:`sim.contact.response.ImpulseCollisionHandler` as its collision hook, then one frame
logged with :meth:`sim.recorder.SimRecorder.on_logger` (particle positions, body poses, the
step's contacts gathered over all its substeps, metrics ``energy/{kinetic,potential,total}``,
``contacts`` and ``penetrations``). Penetrations come from the independent
:class:`sim.penetration.PenetrationChecker`, evaluated on every step's end state.

Energy: kinetic (particles ``m v^2 / 2``, bodies ``m v^2 / 2 + w^T I_world w / 2``) plus
potential (gravity ``-m g . x`` with the origin as reference, springs ``k (l - l0)^2 / 2``).
"""

from __future__ import annotations

import argparse
import hashlib
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from scenes import interrupts
from scenes.registry import (
    add_max_derivative_argument,
    non_negative_float,
    non_negative_int,
    positive_float,
    positive_int,
)
from sim.integrators import INTEGRATORS
from core.rotation import quat_to_matrix
from sim.contact.stage import StageObserver
from sim.stability import SimulationDiverged  # the integrator's per-substep check raises it too

PRECISIONS = ("float64",)
"""The simulator step is float64 throughout (the narrow phase that decides CCD contacts can run in
float32: ``--ccd-precision``)."""
SUPPORTS_STEPS = True
DEFAULT_STEPS = 120
DEFAULT_DT = 1.0 / 60.0
DEFAULT_SUBSTEPS = 8
DEFAULT_DEVICE = "cpu"
DEFAULT_COLLISION_ROUNDS = 8
"""CCD + impulse rounds per substep (:class:`sim.contact.response.ImpulseCollisionHandler`'s
``max_iterations``); a substep still colliding after them falls back to rigid impact zones."""
RESPONSES = ("gauss-seidel", "replayed")
DEFAULT_RESPONSE = "replayed"
"""Collision response of the scenes: the replayed exact solve (the default, and the form that
:func:`sim.rollout.rollout` differentiates, so a scene run and a rollout of the same model take
the same response), or projected Gauss-Seidel impulses (cheaper, but it fails the physics
validation suite's flat drops, slopes, rest and stacks; see
:class:`sim.contact.response.ImpulseCollisionHandler`)."""

BuildFn = Callable[[Any, argparse.Namespace], None]
CCD_PRECISIONS = ("float64", "float32")
"""Precisions of the narrow phase that decides CCD contacts (``--ccd-precision``)."""


CCD_FLAGS = {"precision": "--ccd-precision", "tolerance_scale": "--ccd-tolerance-scale",
             "max_iterations": "--root-max-iterations", "tolerance": "--root-tolerance"}
"""The CLI flag of each ``ccd_options`` key (:func:`add_ccd_arguments`)."""


def ccd_options(args: argparse.Namespace) -> dict:
    """The narrow-phase knobs of ``args`` (``--ccd-*``, ``--root-*``) as the collision
    handler's ``ccd_options`` (only the non-default ones: the defaults run the kernels as
    written)."""
    options = {}
    precision = getattr(args, "ccd_precision", "float64")
    if precision != "float64":
        options["precision"] = precision
    scale = getattr(args, "ccd_tolerance_scale", 1.0)
    if scale != 1.0:
        options["tolerance_scale"] = float(scale)
    for flag, key in (("root_max_iterations", "max_iterations"), ("root_tolerance", "tolerance")):
        value = getattr(args, flag, None)
        if value is not None:
            options[key] = value
    return options


def check_ccd_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuses (``parser.error``, exit code 2, naming the flag) CCD knob values that each flag
    accepts alone but not together, e.g. a ``--root-tolerance`` below float32's range with
    ``--ccd-precision float32``: before the run, not when the collision handler is built."""
    from sim.contact.response import check_ccd_options

    try:
        check_ccd_options(ccd_options(args))
    except ValueError as exc:
        text = str(exc).removeprefix("ccd_options: ")
        key = max((k for k in CCD_FLAGS if text.startswith(k + " ")), key=len, default=None)
        if key is not None:
            text = CCD_FLAGS[key] + text[len(key):]
        parser.error(f"{text} (with --ccd-precision {getattr(args, 'ccd_precision', 'float64')})")


def warp_device(text: str) -> str:
    """argparse type: a Warp device this machine has (``cpu``, ``cuda``, ``cuda:0``, ...)."""
    import contextlib

    import warp as wp

    with contextlib.redirect_stdout(sys.stderr):  # Warp's start-up banner: stdout is for the summary
        wp.init()
    try:
        return str(wp.get_device(text))
    except Exception as exc:
        available = ", ".join(str(d) for d in wp.get_devices())
        raise argparse.ArgumentTypeError(f"{text!r} is not usable here ({exc}); available: {available}") from None


IMPLICIT_FLAGS = {"cg_tolerance": "tolerance", "max_strain_step": "max_strain_step", "contact_passes": "contact_passes"}
"""The implicit integrator's options: CLI destination -> its ``integrator_options`` key."""


def integrator_options(args: argparse.Namespace) -> dict:
    """The implicit integrator's options given on the command line; ValueError naming the flag
    when one is given without ``--integrator implicit``."""
    kind = getattr(args, "integrator", "semi_implicit")
    options = {}
    for flag, key in IMPLICIT_FLAGS.items():
        value = getattr(args, flag, None)
        if value is None:
            continue
        if kind != "implicit":
            raise ValueError(f"--{flag.replace('_', '-')} applies to --integrator implicit only")
        options[key] = (value or None) if key == "max_strain_step" else value
    return options


def add_arguments(parser: argparse.ArgumentParser, cloth: bool = True) -> None:
    """Options of every simulation scene: ``--dt``, ``--substeps``, ``--device``, ...; with
    ``cloth``, the cloth integrator's (``--integrator`` and the implicit one's options)."""
    parser.add_argument("--dt", type=positive_float, default=DEFAULT_DT,
                        help=f"frame time step [s] (default 1/60 = {DEFAULT_DT:.6g})")
    parser.add_argument("--substeps", type=positive_int, default=DEFAULT_SUBSTEPS,
                        help=f"substeps per frame (>= 1; default {DEFAULT_SUBSTEPS})")
    parser.add_argument("--device", type=warp_device, default=DEFAULT_DEVICE,
                        help=f"Warp device, e.g. cpu or cuda:0 (default {DEFAULT_DEVICE})")
    parser.add_argument("--scale", type=positive_float, default=1.0,
                        help="multiply every length of the scene (and gravity, velocities) by this "
                             "factor, masses and times kept: the same motion, scaled (default 1)")
    parser.add_argument("--response", choices=RESPONSES, default=DEFAULT_RESPONSE,
                        help="collision response: Gauss-Seidel impulses or the replayed exact solve "
                             f"that rollouts differentiate (default {DEFAULT_RESPONSE})")
    if cloth:
        parser.add_argument("--integrator", choices=INTEGRATORS, default="semi_implicit",
                            help="cloth springs: semi-implicit Euler (explicit) or backward Euler with a CG solve "
                                 "(default %(default)s)")
        parser.add_argument("--cg-tolerance", type=positive_float, default=None,
                            help="implicit integrator only: CG's relative residual (default 1e-8)")
        parser.add_argument("--max-strain-step", type=non_negative_float, default=None,
                            help="implicit integrator only: halve a substep whose springs' strain grows by more "
                                 "than this (up to 4 times; 0 = never; default 0.1)")
    parser.add_argument("--thickness", type=non_negative_float, default=None,
                        help="contact thickness [m]: the separation the proximity pass keeps between primitives "
                             "(default: the scene's; 0 = 1e-4 x the diagonal of the collidable vertices' box)")
    parser.add_argument("--collision-rounds", type=positive_int, default=DEFAULT_COLLISION_ROUNDS,
                        help="CCD + impulse rounds per substep before the rigid impact-zone fail-safe "
                             f"(>= 1; default {DEFAULT_COLLISION_ROUNDS})")
    add_ccd_arguments(parser)
    if cloth:
        parser.add_argument("--contact-passes", type=non_negative_int, default=None,
                            help="implicit integrator only: constrained re-solves per substep for the particles in "
                                 "contact (0 = collision response after the solve only; default 1)")


def add_ccd_arguments(parser: argparse.ArgumentParser) -> None:
    """The narrow-phase knobs that decide CCD contacts (``--ccd-*``, ``--root-*``; read back by
    :func:`ccd_options`)."""
    parser.add_argument("--ccd-precision", choices=CCD_PRECISIONS, default="float64",
                        help="precision of the narrow phase (and its root solver) that decides the CCD contacts; "
                             "the replayed times of impact and everything else stay float64 (default %(default)s)")
    parser.add_argument("--ccd-tolerance-scale", type=positive_float, default=1.0,
                        help="multiplier of the narrow phase's coefficient and distance error bounds: < 1 fewer "
                             "false positives, false negatives possible; > 1 looser (default 1)")
    parser.add_argument("--root-max-iterations", type=positive_int, default=None,
                        help="the narrow phase's Newton-bisection iteration cap per root (default 256)")
    parser.add_argument("--root-tolerance", type=positive_float, default=None,
                        help="the narrow phase's relative Newton step tolerance (default 2 ulp of the precision)")


def add_rollout_arguments(parser: argparse.ArgumentParser, substeps: int) -> None:
    """Options of the scenes that optimise through :func:`sim.rollout.rollout`: ``--substeps``,
    ``--max-derivative`` (``M``) and the CCD knobs (read back by :func:`rollout_settings`)."""
    from collision.roots import DEFAULT_MAX_DERIVATIVE

    parser.add_argument("--substeps", type=positive_int, default=substeps,
                        help=f"substeps per frame (>= 1; default {substeps})")
    add_max_derivative_argument(parser, DEFAULT_MAX_DERIVATIVE, "; the baseline is unmollified")
    add_ccd_arguments(parser)


@dataclass(frozen=True)
class RolloutSettings:
    """How an inverse scene's rollouts run (:func:`rollout_settings`): ``substeps`` per frame
    (None: the scene's own), ``max_derivative`` ``M`` (None: the rollout's default) and the
    collision handler's ``ccd_options``."""

    substeps: int | None = None
    max_derivative: float | None = None
    ccd_options: dict = field(default_factory=dict)

    def rollout_arguments(self, substeps: int, unmollified: bool = False) -> tuple[int, dict]:
        """(substeps, keyword arguments of :func:`sim.rollout.rollout`) for a scene whose own
        substeps are ``substeps``; ``unmollified`` turns the robust division off (baselines)."""
        from sim.rollout import UNMOLLIFIED_MAX_DERIVATIVE

        kw: dict[str, Any] = {}
        if unmollified:
            kw["max_derivative"] = UNMOLLIFIED_MAX_DERIVATIVE
        elif self.max_derivative is not None:
            kw["max_derivative"] = self.max_derivative
        if self.ccd_options:
            kw["ccd_options"] = dict(self.ccd_options)
        return (self.substeps or substeps), kw


def rollout_settings(args: argparse.Namespace) -> RolloutSettings:
    """The :class:`RolloutSettings` of an inverse scene's parsed options."""
    return RolloutSettings(getattr(args, "substeps", None), getattr(args, "max_derivative", None), ccd_options(args))


def default_args(**overrides: Any) -> argparse.Namespace:
    """A namespace with the CLI defaults (for in-process runs), updated by ``overrides``."""
    ns = argparse.Namespace(seed=0, precision="float64", steps=None, dt=DEFAULT_DT,
                            substeps=DEFAULT_SUBSTEPS, device=DEFAULT_DEVICE, scale=1.0,
                            response=DEFAULT_RESPONSE, integrator="semi_implicit", cg_tolerance=None,
                            max_strain_step=None, contact_passes=None, thickness=None,
                            collision_rounds=DEFAULT_COLLISION_ROUNDS, ccd_precision="float64",
                            ccd_tolerance_scale=1.0, root_max_iterations=None, root_tolerance=None,
                            capture_rounds=False)
    for k, v in overrides.items():
        setattr(ns, k, v)
    return ns


def build_model(build: BuildFn, args: argparse.Namespace):
    """Runs the scene's ``build`` on a fresh builder, finalises it on ``args.device`` and scales
    it by ``args.scale`` (:meth:`sim.model.Model.scaled`)."""
    from sim.builder import ModelBuilder

    builder = ModelBuilder()
    build(builder, args)
    thickness = getattr(args, "thickness", None)
    if thickness is not None:  # the CLI's --thickness overrides the scene's own
        builder.thickness = thickness
    model = builder.finalize(getattr(args, "device", DEFAULT_DEVICE))
    scale = float(getattr(args, "scale", 1.0))
    return model if scale == 1.0 else model.scaled(scale)


DIVERGENCE_FACTOR = 100.0
"""A run stops with :class:`SimulationDiverged` once the kinetic energy exceeds this many times
the scene's energy scale (:meth:`EnergyMeter.reference_scale`): energy is only ever dissipated
or exchanged with gravity, so that much kinetic energy means the explicit springs blew up
(substeps too long for their stiffness), not physics."""


class EnergyMeter:
    """Kinetic and potential energy of a model's states (numpy, float64)."""

    def __init__(self, model) -> None:
        self.g = np.asarray(model.gravity, dtype=np.float64)
        P, B = int(model.particle_count), int(model.body_count)
        self.pm = model.particle_mass.numpy() if P else np.zeros(0)
        if model.spring_count and P:
            self.si = model.spring_indices.numpy().reshape(-1, 2)
            self.rest = model.spring_rest_length.numpy()
            self.k = model.spring_stiffness.numpy()
        else:
            self.si, self.rest, self.k = np.zeros((0, 2), np.int64), np.zeros(0), np.zeros(0)
        self.bm = model.body_mass.numpy() if B else np.zeros(0)
        self.bI = model.body_inertia.numpy().reshape(-1, 3, 3) if B else np.zeros((0, 3, 3))

    def reference_scale(self, state, kinetic: float, potential: float) -> float:
        """Energy scale [J] of a scene: ``|kinetic| + |potential|`` of ``state`` plus the work
        gravity does on all the mass over the diagonal of the state's bounding box (the falls a
        scene of that size allows)."""
        x = state.particle_q.numpy().reshape(-1, 3)
        parts = [x] if len(x) else []
        if len(self.bm):
            parts.append(state.body_q.numpy().reshape(-1, 7)[:, :3])
        pts = np.concatenate(parts) if parts else np.zeros((1, 3))
        extent = float(np.linalg.norm(pts.max(0) - pts.min(0)))
        mass = float(np.sum(self.pm) + np.sum(self.bm))
        scale = abs(kinetic) + abs(potential) + mass * float(np.linalg.norm(self.g)) * extent
        return scale if scale > 0 else 1.0

    def __call__(self, state) -> tuple[float, float]:
        """``(kinetic, potential)`` [J] of ``state``."""
        x = state.particle_q.numpy().reshape(-1, 3)
        v = state.particle_qd.numpy().reshape(-1, 3)
        kin = 0.5 * float(np.sum(self.pm * np.sum(v * v, axis=1)))
        pot = -float(np.sum(self.pm * (x @ self.g)))
        if len(self.k):
            length = np.linalg.norm(x[self.si[:, 1]] - x[self.si[:, 0]], axis=1)
            pot += 0.5 * float(np.sum(self.k * (length - self.rest) ** 2))
        if len(self.bm):
            bq = state.body_q.numpy().reshape(-1, 7)
            bv = state.body_qd.numpy().reshape(-1, 6)
            w, lin = bv[:, :3], bv[:, 3:]
            r = quat_to_matrix(bq[:, 3:] / np.linalg.norm(bq[:, 3:], axis=1, keepdims=True))
            iw = r @ self.bI @ np.swapaxes(r, 1, 2)
            kin += 0.5 * float(np.sum(self.bm * np.sum(lin * lin, axis=1)))
            kin += 0.5 * float(np.einsum("bi,bij,bj->", w, iw, w))
            pot -= float(np.sum(self.bm * (bq[:, :3] @ self.g)))
        return kin, pot


class ContactGatherer(StageObserver):
    """Wraps an :class:`ImpulseCollisionHandler` to collect the contacts of all substeps of a step
    (the handler itself keeps only its last call's)."""

    def __init__(self, handler) -> None:
        super().__init__(handler)
        self.reset()

    def reset(self) -> None:
        self.points: list[np.ndarray] = []
        self.normals: list[np.ndarray] = []
        self.times: list[np.ndarray] = []
        self._elapsed = 0.0

    def save_stats(self):
        """The gathered contacts' and the handler's statistics (see
        ``ImpulseCollisionHandler.save_stats``)."""
        return self.handler.save_stats(), len(self.points), self._elapsed

    def restore_stats(self, stats) -> None:
        """Forgets what calls after :meth:`save_stats` gathered."""
        inner, count, elapsed = stats
        self.handler.restore_stats(inner)
        del self.points[count:], self.normals[count:], self.times[count:]
        self._elapsed = elapsed

    def __call__(self, state_in, state_pred, h: float):
        out = self.handler(state_in, state_pred, h)
        self._gather(h)
        return out

    def _gather(self, h: float) -> None:
        if len(self.handler.last_contacts):
            self.points.append(np.asarray(self.handler.last_contacts, dtype=np.float64).reshape(-1, 3))
            self.normals.append(np.asarray(self.handler.last_normals, dtype=np.float64).reshape(-1, 3))
            # times of impact in seconds from the start of the step
            self.times.append(self._elapsed + np.asarray(self.handler.last_times, dtype=np.float64).reshape(-1))
        self._elapsed += h

    def contacts(self) -> dict[str, np.ndarray]:
        if not self.points:
            return {"points": np.zeros((0, 3)), "normals": np.zeros((0, 3)), "toi": np.zeros(0)}
        return {"points": np.concatenate(self.points), "normals": np.concatenate(self.normals),
                "toi": np.concatenate(self.times)}


def state_sha256(arrays: dict[str, Any]) -> str:
    """The SHA-256 (hex) of a state's bits: ``particle_q``, ``particle_qd``, ``body_q`` and
    ``body_qd`` of ``arrays`` (numpy arrays, as :meth:`sim.model.State.numpy` returns), in that
    order; the summaries' ``state_sha256``."""
    digest = hashlib.sha256()
    for key in ("particle_q", "particle_qd", "body_q", "body_qd"):
        digest.update(np.ascontiguousarray(arrays[key]).tobytes())
    return digest.hexdigest()


def simulate(
    build: BuildFn,
    args: argparse.Namespace,
    log: Any | None = None,
    *,
    name: str = "sim",
    progress: bool = True,
    prepare: Callable[[Any], Any] | None = None,
    observer: Callable[[int, Any, dict[str, Any]], None] | None = None,
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Builds and runs a simulation scene.

    Args:
        build: ``build(builder, args)`` of the scene.
        args: Parsed options (``steps`` None -> :data:`DEFAULT_STEPS`, ``dt``, ``substeps``,
            ``device``).
        log: An open :class:`sim.logging.RerunLogger` to record into, or None (no recording).
        name: Scene name (progress bar label, summary).
        progress: Show a tqdm bar on stderr (only when stderr is a terminal).
        prepare: ``prepare(model) -> model`` applied to the built model before the run (e.g. a
            perturbation of its initial positions for a noise floor).
        observer: ``observer(step, state, info)`` after every step (``step`` from 1), with
            ``info`` holding ``kinetic`` and ``potential`` [J] and ``contacts`` (points, normals
            and times of impact ``toi`` [s from the step's start] of the step's contacts).

    Returns:
        ``(summary, final_state)``: the JSON summary and the final state as numpy arrays.
    """
    from tqdm import tqdm

    from sim.contact.contacts import ContactLimitExceeded
    from sim.contact.response import ImpulseCollisionHandler
    from sim.integrators import make_integrator
    from sim.penetration import PenetrationChecker
    from sim.stability import DivergenceGuard, check_explicit_substep

    steps = int(args.steps) if getattr(args, "steps", None) is not None else DEFAULT_STEPS
    dt = float(getattr(args, "dt", DEFAULT_DT))
    substeps = int(getattr(args, "substeps", DEFAULT_SUBSTEPS))

    model = build_model(build, args)
    if prepare is not None:
        model = prepare(model)
    kind = getattr(args, "integrator", "semi_implicit")
    options = integrator_options(args)
    flags = f"raise --substeps (now {substeps}), lower --dt (now {dt:g} s)"
    if kind != "implicit":
        refused = check_explicit_substep(model, dt / substeps)
        if refused is not None:
            raise SimulationDiverged(f"{name}: refused: {refused}: {flags} or use --integrator implicit")
    integrator = make_integrator(model, kind, **options)
    handler = ImpulseCollisionHandler(
        model, max_iterations=int(getattr(args, "collision_rounds", DEFAULT_COLLISION_ROUNDS)),
        differentiable=getattr(args, "response", DEFAULT_RESPONSE) == "replayed", ccd_options=ccd_options(args),
        capture_rounds=bool(getattr(args, "capture_rounds", False)))
    gatherer = ContactGatherer(handler)
    integrator.collision_handler = gatherer
    checker = PenetrationChecker(model)
    energy = EnergyMeter(model)
    recorder = None
    if log is not None:
        from sim.recorder import SimRecorder

        recorder = SimRecorder.on_logger(log, model)

    state, nxt = model.state(), model.state()
    integrator.divergence_guard = DivergenceGuard(model, state, steps * dt)
    k0, p0 = energy(state)
    e0 = k0 + p0
    divergence_limit = DIVERGENCE_FACTOR * energy.reference_scale(state, k0, p0)
    rep0 = checker.check(state)
    if rep0.count:
        raise RuntimeError(f"{name}: the initial state already has {rep0.count} penetrations")
    if log is not None and hasattr(log, "keep_partial"):
        # the input is valid and stepping starts: from here an interruption (Ctrl-C, an error)
        # keeps the frames recorded so far as a complete, readable file
        log.keep_partial = True
    e_max = e0
    total_contacts = 0
    max_pen = 0
    max_depth = 0.0
    pen_frames = 0
    finite = True
    step_times = []
    start = time.perf_counter()
    bar = tqdm(total=steps, desc=name, unit="step", file=sys.stderr, disable=None if progress else True, leave=False)
    try:
        for k in range(steps):
            interrupts.raise_pending()
            t0 = time.perf_counter()
            gatherer.reset()
            try:
                integrator.step(state, nxt, dt, substeps)
            except (SimulationDiverged, ContactLimitExceeded) as exc:
                raise SimulationDiverged(f"{name}: step {k + 1}: {exc}: {flags}") from None
            state, nxt = nxt, state
            step_times.append(time.perf_counter() - t0)
            contacts = gatherer.contacts()
            n_contacts = len(contacts["points"])
            total_contacts += n_contacts
            kin, pot = energy(state)
            e = kin + pot
            finite &= math.isfinite(e)
            if not math.isfinite(kin) or kin > divergence_limit:
                raise SimulationDiverged(
                    f"{name}: the simulation diverged at step {k + 1}: kinetic energy {kin:.3g} J exceeds "
                    f"{DIVERGENCE_FACTOR:g}x the scene's energy scale ({divergence_limit / DIVERGENCE_FACTOR:.3g} J). "
                    f"Explicit springs need substeps shorter than about 2 / sqrt(k / m): raise --substeps "
                    f"(now {substeps}), lower --dt (now {dt:g} s) or use --integrator implicit"
                )
            e_max = max(e_max, e) if math.isfinite(e) else e_max
            if observer is not None:
                observer(k + 1, state, {"kinetic": kin, "potential": pot, "contacts": contacts})
            rep = checker.check(state)
            max_pen = max(max_pen, rep.count)
            max_depth = max(max_depth, rep.max_depth)
            pen_frames += rep.count > 0
            if recorder is not None:
                recorder.record(
                    k + 1, (k + 1) * dt, state,
                    contacts=contacts if n_contacts else None,
                    metrics={"energy/kinetic": kin, "energy/potential": pot, "energy/total": e,
                             "contacts": n_contacts, "penetrations": rep.count},
                )
            bar.update(1)
    except BaseException as exc:
        if recorder is not None:
            recorder.close(type(exc), exc, exc.__traceback__)
        raise
    finally:
        bar.close()
    if recorder is not None:
        recorder.close()
    wall = time.perf_counter() - start
    kin, pot = energy(state)
    e_end = kin + pot
    scale = abs(e0) if abs(e0) > 0 else 1.0
    final = state.numpy()
    summary = {
        "scene": name,
        "steps": steps,
        "dt": dt,
        "substeps": substeps,
        "integrator": kind,
        "response": getattr(args, "response", DEFAULT_RESPONSE),
        "thickness": float(model.thickness),
        "collision_rounds": int(handler.max_iterations),
        "ccd_options": dict(handler.ccd_options),
        "cg_iterations": int(getattr(integrator, "total_iterations", 0)),
        "refined_substeps": int(getattr(integrator, "refinements", 0)),
        "contact_constrained": int(getattr(integrator, "total_constrained", 0)),
        "device": str(model.device),
        "scale": float(getattr(args, "scale", 1.0)),
        "components": sorted(model.components),
        "particles": int(model.particle_count),
        "bodies": int(model.body_count),
        "stepping_seconds": round(wall, 4),  # the stepping loop alone (wall_time_s: the whole run)
        "steps_per_second": steps / wall if wall > 0 else None,
        "step_ms_mean": 1e3 * float(np.mean(step_times)) if step_times else 0.0,
        "contacts": int(total_contacts),
        "penetrations": int(max_pen),
        "penetration_frames": int(pen_frames),
        "max_penetration_depth": float(max_depth),
        "energy_initial": e0,
        "energy_final": e_end,
        "energy_drift": (e_end - e0) / scale,
        "energy_max_ratio": e_max / e0 if e0 > 0 else None,
        "energy_finite": bool(finite and math.isfinite(e_end)),
        "failsafe_count": int(handler.failsafe_count),
        "state_sha256": state_sha256(final),
    }
    if handler.capture_rounds:  # graphs of CCD rounds recorded and launched
        summary["captured_round_graphs"] = int(handler.captured_round_graphs)
    return summary, final


def run_scene(build: BuildFn, args: argparse.Namespace, log: Any, name: str) -> dict[str, Any]:
    """The ``run(args, log)`` of a simulation scene: :func:`simulate` with recording."""
    summary, _ = simulate(build, args, log, name=name)
    return summary

"""Lifted events: a collision that may or may not happen, as roots an optimiser can move.

design.md "Lifted events": a scene designates a primitive pair (vertex-face or edge-edge) and a
window of steps ``[first, last]``. The pair's motion linearised over the window,
``x(s) = x(t_first) + s (x(t_last) - x(t_first))``, gives a coplanarity cubic whose three roots
(real or complex, slots ``t-, tM, t+`` of design.md) are outputs of :func:`sim.rollout.rollout`
(``res.event_roots``, seconds from the window's start) with the paper's mollified implicit
derivative (:func:`collision.ccd.coplanarity_roots`). A miss is a complex or out-of-window root;
:func:`root_loss` (eq. ``loss``) and :func:`complex_conjugate_loss` (eq.
``complexconjugateloss``) pull it onto the real axis and into the window, and
``res.event_coords`` (where the pair is at each root's real part) lets a loss pull a real root
inside the triangle. Once the collision really happens, the replayed contact's gradients take
over (the trajectory outputs).

A :class:`SphereEvent` lifts a pair of sphere bodies the same way: their centres' relative
motion linearised over the window, ``d(s) = d_first + s (d_last - d_first)``, gives the paper's
quadratic ``|d(s)|^2 = (r_a + r_b)^2`` whose two roots (slots ``t-, t+``) come back in
``res.sphere_event_roots`` (:func:`sphere_event_roots`). For spheres in free flight (no forces,
no contact of either inside the window) the linearisation is exact.

Vertices are named by what they belong to: :func:`particle`, :func:`body_vertex` (the k-th
surface vertex of body b, in the order of the mesh given to ``add_rigid_body`` after unused
vertices are dropped) and :func:`static_vertex`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from collision.roots import DEFAULT_MAX_DERIVATIVE
from core.rotation import quat_rotate

KINDS = ("vertex_face", "edge_edge")
COORDINATE_TIME_LIMIT = 1.0e6
"""Real parts of roots (in windows) beyond this are clamped before the closest-point
coordinates are evaluated: an escaping root sits at ``±t_max = ±1e150``, where positions would
overflow, and coordinates that far out mean nothing."""


@dataclass(frozen=True)
class VertexRef:
    """A collidable vertex: ``kind`` "particle" (index), "body" (body, surface vertex) or "static"
    (index into the static colliders' vertices, in order of addition)."""

    kind: str
    index: int
    vertex: int = 0


def particle(i: int) -> VertexRef:
    return VertexRef("particle", int(i))


def body_vertex(body: int, k: int) -> VertexRef:
    return VertexRef("body", int(body), int(k))


def static_vertex(j: int) -> VertexRef:
    return VertexRef("static", int(j))


@dataclass(frozen=True)
class Event:
    """A designated primitive pair and its window.

    Attributes:
        kind: "vertex_face" (vertices: the point, then the triangle's three corners) or
            "edge_edge" (edge a's two endpoints, then edge b's).
        vertices: four :class:`VertexRef`.
        window: (first, last) step indices of the rollout, ``0 <= first < last <= steps``.
    """

    kind: str
    vertices: tuple
    window: tuple


@dataclass(frozen=True)
class SphereEvent:
    """A designated pair of sphere bodies and its window.

    Attributes:
        body_a, body_b: the two spheres' body indices (distinct).
        window: (first, last) step indices of the rollout, ``0 <= first < last <= steps``.
    """

    body_a: int
    body_b: int
    window: tuple


def _check_window(window, steps: int, where: str) -> None:
    if not isinstance(window, (tuple, list)) or len(window) != 2 \
            or not all(isinstance(w, (int, np.integer)) and not isinstance(w, bool) for w in window):
        raise ValueError(f"{where}.window must be two step indices (first, last)")
    first, last = (int(w) for w in window)
    if not 0 <= first < last <= steps:
        raise ValueError(f"{where}.window must satisfy 0 <= first < last <= steps ({steps}), got {window}")


def check_sphere_event(model, ev: SphereEvent, steps: int, where: str) -> SphereEvent:
    """Validates a :class:`SphereEvent` (ValueError naming ``where`` and the field)."""
    spheres = set(int(b) for b in model.sphere_body.numpy()) if model.sphere_count else set()
    for field_name in ("body_a", "body_b"):
        b = getattr(ev, field_name)
        if isinstance(b, bool) or not isinstance(b, (int, np.integer)) or int(b) not in spheres:
            raise ValueError(f"{where}.{field_name} must be the body index of a sphere, got {b!r}")
    if int(ev.body_a) == int(ev.body_b):
        raise ValueError(f"{where}: body_a and body_b must be two different spheres")
    _check_window(ev.window, steps, where)
    return ev


def _body_vertex_table(model):
    """(body, k) -> row of ``model.shape_vertices``."""
    if model.shape_vertex_body is None or model.body_count == 0:
        return {}, np.zeros((0, 3))
    owner = model.shape_vertex_body.numpy()
    table = {}
    counts = np.zeros(model.body_count, dtype=np.int64)
    for row, b in enumerate(owner):
        table[(int(b), int(counts[b]))] = row
        counts[b] += 1
    return table, model.shape_vertices.numpy()


def check_events(model, events, steps: int) -> list[Event]:
    """Validates ``events`` against the model and the rollout length (ValueError naming the
    offending event and field)."""
    if events is None:
        raise ValueError("events must be a sequence of sim.events.Event (or empty)")
    table, _ = _body_vertex_table(model)
    n_static = 0 if model.static_vertices is None else model.static_vertices.shape[0]
    out = []
    for e, ev in enumerate(events):
        if isinstance(ev, SphereEvent):
            out.append(check_sphere_event(model, ev, steps, f"events[{e}]"))
            continue
        if not isinstance(ev, Event):
            raise ValueError(f"events[{e}] must be a sim.events.Event or SphereEvent, got {type(ev).__name__}")
        if ev.kind not in KINDS:
            raise ValueError(f"events[{e}].kind must be one of {KINDS}, got {ev.kind!r}")
        if len(ev.vertices) != 4 or not all(isinstance(v, VertexRef) for v in ev.vertices):
            raise ValueError(f"events[{e}].vertices must be four sim.events.VertexRef")
        for v in ev.vertices:
            ok = ((v.kind == "particle" and 0 <= v.index < model.particle_count)
                  or (v.kind == "body" and (v.index, v.vertex) in table)
                  or (v.kind == "static" and 0 <= v.index < n_static))
            if not ok:
                raise ValueError(f"events[{e}].vertices: {v} is not a vertex of the model")
        if len(set(ev.vertices)) != 4:
            raise ValueError(f"events[{e}].vertices must be four distinct vertices")
        _check_window(ev.window, steps, f"events[{e}]")
        out.append(ev)
    return out


def event_positions(model, events, particle_q, body_q):
    """World positions of each event's four vertices at its window's ends.

    Args:
        model: the :class:`sim.model.Model` the events refer to.
        events: the checked :class:`Event` s.
        particle_q: the rollout's particle trajectory, torch (N+1, P, 3).
        body_q: the rollout's body poses, torch (N+1, B, 7).

    Returns:
        (x_first, x_last): torch float64 (E, 4, 3) each, differentiable w.r.t. the trajectories.
    """
    import torch

    table, local = _body_vertex_table(model)
    static = model.static_vertices.numpy() if model.static_vertices is not None else np.zeros((0, 3))
    ends = []
    for end in (0, 1):
        rows = []
        for ev in events:
            step = int(ev.window[end])
            pts = []
            for v in ev.vertices:
                if v.kind == "particle":
                    pts.append(particle_q[step, v.index])
                elif v.kind == "body":
                    pose = body_q[step, v.index]
                    r = torch.as_tensor(local[table[(v.index, v.vertex)]], dtype=torch.float64)
                    pts.append(pose[:3] + quat_rotate(pose[3:7], r))
                else:
                    pts.append(torch.as_tensor(static[v.index], dtype=torch.float64))
            rows.append(torch.stack(pts))
        ends.append(torch.stack(rows) if rows else torch.zeros((0, 4, 3), dtype=torch.float64))
    return ends[0], ends[1]


def closest_point_coordinates(kind_edge, y):
    """Closest-point coordinates of the pair at positions y (E, 4, 3): vertex-face: barycentric
    (w1, w2, w3) of the point's projection onto the triangle's plane (inside iff all >= 0);
    edge-edge: (s_a, s_b, 0), the parameters of the two lines' closest points (overlap iff both
    in [0, 1]). Unclamped, so a loss has a gradient outside as well. Degenerate triangles and
    parallel edges fall back to finite values (a tiny Tikhonov term)."""
    import torch

    p, a, b, c = y[:, 0], y[:, 1], y[:, 2], y[:, 3]
    # vertex-face: solve the 2x2 Gram system for the projection
    e1, e2, d = b - a, c - a, p - a
    g11, g12, g22 = (e1 * e1).sum(-1), (e1 * e2).sum(-1), (e2 * e2).sum(-1)
    r1, r2 = (d * e1).sum(-1), (d * e2).sum(-1)
    scale = g11 + g22
    det = g11 * g22 - g12 * g12 + 1e-30 * scale * scale + 1e-300
    u = (g22 * r1 - g12 * r2) / det
    v = (g11 * r2 - g12 * r1) / det
    face = torch.stack([1.0 - u - v, u, v], dim=-1)
    # edge-edge: the closest points of the lines through (p, a) and (b, c)
    da, db, r = a - p, c - b, p - b
    aa, bb, ab = (da * da).sum(-1), (db * db).sum(-1), (da * db).sum(-1)
    ra, rb = (da * r).sum(-1), (db * r).sum(-1)
    den = aa * bb - ab * ab + 1e-30 * (aa + bb) ** 2 + 1e-300
    sa = (ab * rb - bb * ra) / den
    sb = (aa * rb - ab * ra) / den
    edge = torch.stack([sa, sb, torch.zeros_like(sa)], dim=-1)
    return torch.where(kind_edge[:, None], edge, face)


def event_outputs(model, events, particle_q, body_q, dt: float, max_derivative: float = DEFAULT_MAX_DERIVATIVE,
                  derivative: str = "mollified"):
    """Roots [s from the window's start] (E, 3, 2) and closest-point coordinates at each root's
    real part (E, 3, 3) of the events (see the module docstring); ``derivative`` as in
    :func:`collision.ccd.coplanarity_roots`."""
    import torch

    from collision.ccd import coplanarity_roots

    if not events:
        return torch.zeros((0, 3, 2), dtype=torch.float64), torch.zeros((0, 3, 3), dtype=torch.float64)
    x_first, x_last = event_positions(model, events, particle_q, body_q)
    fractions = coplanarity_roots(x_first, x_last, max_derivative, derivative)
    duration = torch.tensor([(ev.window[1] - ev.window[0]) * dt for ev in events], dtype=torch.float64)
    roots = fractions * duration[:, None, None]
    kind_edge = torch.tensor([ev.kind == "edge_edge" for ev in events])
    coords = []
    for slot in range(3):
        s = fractions[:, slot, 0].clamp(-COORDINATE_TIME_LIMIT, COORDINATE_TIME_LIMIT)
        y = x_first + s[:, None, None] * (x_last - x_first)
        coords.append(closest_point_coordinates(kind_edge, y))
    return roots, torch.stack(coords, dim=1)


def sphere_event_roots(model, events, body_q, dt: float, max_derivative: float = DEFAULT_MAX_DERIVATIVE,
                       derivative: str = "mollified"):
    """Roots [s from the window's start] (E, 2, 2) of the :class:`SphereEvent` s: slots
    ``(t-, t+)``, (Re, Im), of ``|d_first + s (d_last - d_first)|^2 = R^2`` (``R = r_a + r_b``
    plus the model's thickness, the distance the contacts keep) times the
    window's duration (the module docstring), differentiable w.r.t. ``body_q`` (N+1, B, 7)
    with the mollified derivative (``derivative`` as in :func:`collision.roots.quadratic_roots`).
    The constant term is factored, ``(|d| - R)(|d| + R)``, exact to rounding near touching."""
    import torch

    from collision.roots import quadratic_roots

    if not events:
        return torch.zeros((0, 2, 2), dtype=torch.float64)
    radius = dict(zip((int(b) for b in model.sphere_body.numpy()), model.sphere_radius.numpy()))
    rows = []
    for ev in events:
        first, last = (int(w) for w in ev.window)
        d_first = body_q[first, ev.body_a, :3] - body_q[first, ev.body_b, :3]
        delta = body_q[last, ev.body_a, :3] - body_q[last, ev.body_b, :3] - d_first
        reach = float(radius[int(ev.body_a)] + radius[int(ev.body_b)]) + float(model.thickness)
        dist = d_first.norm()
        rows.append(torch.stack([delta.dot(delta), 2.0 * d_first.dot(delta), (dist - reach) * (dist + reach)]))
    fractions = quadratic_roots(torch.stack(rows), max_derivative=max_derivative, derivative=derivative)
    duration = torch.tensor([(ev.window[1] - ev.window[0]) * dt for ev in events], dtype=torch.float64)
    return fractions * duration[:, None, None]


# ------------------------------------------------------------------------------ losses


def root_loss(root, target, coefficients=None, coefficient_target=None):
    """Eq. ``loss``: ``0.5 (|t - t_L|^2 + |p - p_L|^2)`` for one tracked root.

    Args:
        root: torch (..., 2) (Re, Im) of the tracked root.
        target: (Re, Im) of the target (Im 0 for a real target: a collision).
        coefficients: optional: the cubic's coefficients, regularised towards ``coefficient_target``.
        coefficient_target: the coefficients' target (used with ``coefficients``).
    """
    import torch

    target = torch.as_tensor(target, dtype=torch.float64)
    loss = 0.5 * ((root - target) ** 2).sum(-1)
    if coefficients is not None:
        loss = loss + 0.5 * ((coefficients - torch.as_tensor(coefficient_target, dtype=torch.float64)) ** 2).sum(-1)
    return loss


def complex_conjugate_loss(root_plus, root_minus, target):
    """Eq. ``complexconjugateloss``: the tracked root at ``t_L`` and its partner at the conjugate;
    only the partner's real part enters (the paper: it is enough), which gives a gradient
    towards the real axis from below the ``c~ = 0`` parabola where the imaginary part is 0."""
    import torch

    target = torch.as_tensor(target, dtype=torch.float64)
    return 0.5 * (((root_plus - target) ** 2).sum(-1) + (root_minus[..., 0] - target[0]) ** 2)


class BranchTracker:
    """Keeps following the same root across optimiser iterations (the cubic's "Branch
    Selection" and "Examples" subsections): slots change roles when the escaping root changes
    sign (``q`` crosses 0), when the single real root switches between ``t+`` and ``t-`` (``c^``
    changes sign), and when the tracked root merges with another into a complex pair (the
    larger real root goes on as the member with positive imaginary part, the smaller as the
    negative one) or a pair splits back (positive imaginary part -> the larger real root; with a
    ``target`` time given to :meth:`update`, the one nearer the target: an optimiser wants the root
    it can move there, and the other one may merge again right away).

    Args:
        slot: the slot tracked at the start (design.md: 0 ``t-``, 1 ``tM``, 2 ``t+``).
    """

    ESCAPING = 1.0e100  # beyond this a root is the escaping one (t_max = 1e150)

    def __init__(self, slot: int = 2):
        if slot not in (0, 1, 2):
            raise ValueError(f"slot must be 0, 1 or 2, got {slot!r}")
        self.slot = slot
        self.previous = None  # (re, im) of the tracked root at the last update
        self.real_count = None  # how many of the three roots were real at the last update

    def update(self, roots, target: float | None = None) -> int:
        """The slot of the tracked root among ``roots`` (3, 2) (numpy or torch, one event);
        ``target``: the time a loss pulls the root to (same units), which picks the member of a
        pair that splits."""
        r = np.asarray(roots.detach().cpu().numpy() if hasattr(roots, "detach") else roots, dtype=np.float64)
        if self.previous is None:
            self.previous = r[self.slot].copy()
            self.real_count = sum(1 for k in range(3) if r[k, 1] == 0.0)
            return self.slot
        re0, im0 = self.previous
        if abs(re0) >= self.ESCAPING:
            # the escaping root: it may come back from the other side (q changes sign)
            escaping = [k for k in range(3) if abs(r[k, 0]) >= self.ESCAPING]
            if escaping:
                same_side = [k for k in escaping if np.sign(r[k, 0]) == np.sign(re0)]
                self.slot = (same_side or escaping)[0]
                self.previous = r[self.slot].copy()
                self.real_count = sum(1 for k in range(3) if r[k, 1] == 0.0)
                return self.slot
        finite = [k for k in range(3) if abs(r[k, 0]) < self.ESCAPING] or [0, 1, 2]
        real_count = sum(1 for k in range(3) if r[k, 1] == 0.0)
        candidates = finite
        if real_count == self.real_count:
            # no pair merged or split since the last update: a real root stays real, a complex
            # one complex on its side of the axis (a real root running off towards infinity
            # is otherwise nearer a complex pair than its own new value: seed 42 of tunnel)
            # (from all three: a real root may just have run past ESCAPING)
            same = [k for k in range(3) if (r[k, 1] == 0.0) == (im0 == 0.0) and np.sign(r[k, 1]) == np.sign(im0)]
            candidates = same or finite
        nearest = min(candidates, key=lambda k: abs(r[k, 0] - re0) + abs(r[k, 1] - im0))
        if im0 == 0.0 and r[nearest, 1] != 0.0:
            # merged into a pair: the larger of the two real roots goes on as +Im
            sign = 1.0 if re0 >= r[nearest, 0] else -1.0
            nearest = next(k for k in range(3) if r[k, 1] * sign > 0.0)
        elif im0 != 0.0 and r[nearest, 1] == 0.0:
            # a pair split: +Im goes on as the larger of the two new real roots, -Im the smaller
            pair = sorted(sorted(finite, key=lambda k: abs(r[k, 0] - re0))[:2], key=lambda k: r[k, 0])
            if target is not None:
                nearest = min(pair, key=lambda k: abs(r[k, 0] - target))
            else:
                nearest = pair[-1] if im0 > 0.0 else pair[0]
        self.slot = nearest
        self.previous = r[self.slot].copy()
        self.real_count = real_count
        return self.slot

"""DiffTaichi's billiards method, written in Taichi for the comparison in ``benchmarks/billiards.py``.

The method of taichi-dev/difftaichi ``examples/billiards.py`` (at 9f4ee522), re-implemented from
its description: 11 balls (a cue ball and a 4-row rack of 10) of radius 0.03 and elasticity 0.8
in the plane, equal masses, no friction, dt 0.003, 1023 steps, float32. Each step tests every
ordered pair at the positions one step ahead (``x + dt v``); a pair closer than ``2 r`` that
approaches gets the impulse ``-(1 + e) / 2 (n . v_rel) n`` (equal masses) and the position
correction ``toi * impulse``, where ``toi = (|d| - 2 r) / min(-1e-3, n . v_rel)`` is a clamped
linear estimate of the time since contact. All pairs act at once. The loss is the squared
distance of the last rack ball from the goal after the last step, and ``ti.ad.Tape`` gives its
gradient with respect to the cue's initial position and velocity.

Imported by the benchmark only (taichi is in the ``difftaichi`` extra, not in ``make test``).
"""


import numpy as np

RADIUS = 0.03
ELASTICITY = 0.8
DT = 0.003
STEPS = 1024  # time levels: 1023 steps
LAYERS = 4
GOAL = (0.9, 0.75)


def rack_positions() -> np.ndarray:
    """The rack's ball centres (10, 2) [m]: row ``i`` (0..3) holds ``i + 1`` balls at
    ``x = 0.5 + 2 r i``, ``y = 0.5 + 2 r j - 0.7 r i``."""
    out = []
    for i in range(LAYERS):
        for j in range(i + 1):
            out.append((i * 2 * RADIUS + 0.5, j * 2 * RADIUS + 0.5 - i * RADIUS * 0.7))
    return np.asarray(out, dtype=np.float64)


class DiffTaichiBilliards:
    """The anchor: ``loss_and_grad(cue_pos, cue_vel)`` runs one forward and backward pass."""

    def __init__(self, threads: int = 1):
        import taichi as ti

        ti.init(arch=ti.cpu, default_fp=ti.f32, cpu_max_num_threads=threads, flatten_if=True, log_level=ti.WARN)
        self.ti = ti
        n = 1 + LAYERS * (LAYERS + 1) // 2
        self.n = n
        self.target = n - 1
        real = ti.f32
        self.x = ti.Vector.field(2, real)
        self.v = ti.Vector.field(2, real)
        self.x_inc = ti.Vector.field(2, real)
        self.impulse = ti.Vector.field(2, real)
        self.start_x = ti.Vector.field(2, real)
        self.start_v = ti.Vector.field(2, real)
        self.loss = ti.field(real)
        ti.root.dense(ti.i, STEPS).dense(ti.j, n).place(self.x, self.v, self.x_inc, self.impulse)
        ti.root.place(self.start_x, self.start_v, self.loss)
        ti.root.lazy_grad()
        x, v, x_inc, impulse = self.x, self.v, self.x_inc, self.impulse
        start_x, start_v, loss = self.start_x, self.start_v, self.loss
        target = self.target
        goal_x, goal_y = GOAL

        @ti.func
        def pair(t, i, j):
            gain = ti.Vector([0.0, 0.0])
            shift = ti.Vector([0.0, 0.0])
            if i != j:
                ahead = (x[t, i] + DT * v[t, i]) - (x[t, j] + DT * v[t, j])
                gap = ahead.norm()
                closing = v[t, i] - v[t, j]
                if gap < 2 * RADIUS:
                    normal = ti.Vector.normalized(ahead, 1e-6)
                    along = normal.dot(closing)
                    if along < 0:
                        gain = -(1 + ELASTICITY) * 0.5 * along * normal
                        since = (gap - 2 * RADIUS) / ti.min(-1e-3, along)
                        shift = ti.min(since - DT, 0) * gain
            x_inc[t + 1, i] += shift
            impulse[t + 1, i] += gain

        @ti.kernel
        def collide(t: ti.i32):
            for i in range(n):
                for j in range(i):
                    pair(t, i, j)
            for i in range(n):
                for j in range(i + 1, n):
                    pair(t, i, j)

        @ti.kernel
        def advance(t: ti.i32):
            for i in range(n):
                v[t, i] = v[t - 1, i] + impulse[t, i]
                x[t, i] = x[t - 1, i] + DT * v[t, i] + x_inc[t, i]

        @ti.kernel
        def final_loss(t: ti.i32):
            loss[None] = (x[t, target][0] - goal_x) ** 2 + (x[t, target][1] - goal_y) ** 2

        @ti.kernel
        def place_cue():
            x[0, 0] = start_x[None]
            v[0, 0] = start_v[None]

        @ti.kernel
        def clear():
            for t, i in ti.ndrange(STEPS, n):
                impulse[t, i] = ti.Vector([0.0, 0.0])
                x_inc[t, i] = ti.Vector([0.0, 0.0])

        self._collide, self._advance, self._final_loss = collide, advance, final_loss
        self._place_cue, self._clear = place_cue, clear
        rack = rack_positions()
        for k in range(len(rack)):
            x[0, k + 1] = rack[k].tolist()
            v[0, k + 1] = [0.0, 0.0]

    def _forward(self) -> None:
        self._place_cue()
        for t in range(1, STEPS):
            self._collide(t - 1)
            self._advance(t)
        self._final_loss(STEPS - 1)

    def loss_and_grad(self, cue_pos, cue_vel) -> tuple[float, np.ndarray]:
        """(loss [m^2], gradient w.r.t. (x, y, vx, vy)) of one shot."""
        self.start_x[None] = [float(c) for c in cue_pos]
        self.start_v[None] = [float(c) for c in cue_vel]
        self._clear()
        with self.ti.ad.Tape(self.loss):
            self._forward()
        grad = np.array([self.start_x.grad[None][0], self.start_x.grad[None][1],
                         self.start_v.grad[None][0], self.start_v.grad[None][1]], dtype=np.float64)
        return float(self.loss[None]), grad

    def target_position(self) -> np.ndarray:
        """The target ball's position after the last forward pass [m]."""
        p = self.x[STEPS - 1, self.target]
        return np.array([p[0], p[1]], dtype=np.float64)

    def optimise(self, cue_pos, cue_vel, iters: int = 200, lr: float = 0.01, tolerance: float = 0.005,
                 stop_at_zero_gradient: bool = False):
        """Plain gradient descent (DiffTaichi's), ``iters`` steps at most (``iters + 1`` rollouts: the
        start and each step's shot, as the billiards scene counts them), stopping early once
        the target is within ``tolerance`` [m] of the goal (and, with ``stop_at_zero_gradient``,
        at an exactly zero gradient: every later iterate would be the same). Returns a dict of
        the run."""
        import time

        z = np.concatenate([np.asarray(cue_pos, dtype=np.float64), np.asarray(cue_vel, dtype=np.float64)])
        losses, distances, seconds = [], [], []
        reached = zero = None
        for it in range(iters + 1):
            t0 = time.perf_counter()
            loss, grad = self.loss_and_grad(z[:2], z[2:])
            seconds.append(time.perf_counter() - t0)
            losses.append(loss)
            distances.append(float(np.linalg.norm(self.target_position() - np.asarray(GOAL))))
            if distances[-1] < tolerance:
                reached = it
                break
            if stop_at_zero_gradient and not np.any(grad != 0.0):
                zero = it
                break
            if it == iters:
                break
            z = z - lr * grad
        return {"losses": losses, "distances": distances, "seconds": seconds, "reached": reached,
                "zero_gradient_at": zero, "final": z.tolist()}

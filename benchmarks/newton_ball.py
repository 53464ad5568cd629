"""Newton's ``diffsim_ball`` (newton 1.8, ``newton/examples/diffsim/example_diffsim_ball.py``),
headless on the CPU, for the side-by-side in ``benchmarks/inverse.py``.

The problem, contact parameters, solver (semi-implicit, penalty contact, float32), 36 frames of
8 substeps and the optimiser (plain gradient descent, rate 0.02, on the squared distance) are the
example's; only the viewer and the CUDA graph capture (CUDA only) are left out. Its gradient
check is the example's own: central differences with step 1e-3 of the same forward.
"""

from __future__ import annotations

import time

import numpy as np
import warp as wp

TARGET = (0.0, -2.0, 1.5)
FRAMES, SUBSTEPS, FPS = 36, 8, 60
TRAIN_RATE = 0.02


@wp.kernel
def _loss_kernel(pos: wp.array(dtype=wp.vec3), target: wp.vec3, loss: wp.array(dtype=float)):
    delta = pos[0] - target
    loss[0] = wp.dot(delta, delta)


class NewtonBall:
    """The example's model, states and forward, without a viewer (``device`` "cpu")."""

    def __init__(self, start_velocity=(0.0, 5.0, -5.0), device: str = "cpu"):
        import newton

        self.device = device
        self.sim_dt = 1.0 / FPS / SUBSTEPS
        with wp.ScopedDevice(device):
            scene = newton.ModelBuilder(up_axis=newton.Axis.Z)
            scene.add_particle(pos=wp.vec3(0.0, -0.5, 1.0), vel=wp.vec3(*start_velocity), mass=1.0)
            ke, kf, kd, mu = 1.0e4, 0.0, 1.0e1, 0.2
            cfg = newton.ModelBuilder.ShapeConfig(ke=ke, kf=kf, kd=kd, mu=mu)
            scene.add_shape_box(body=-1, xform=wp.transform(wp.vec3(0.0, 2.0, 1.0), wp.quat_identity()),
                                hx=1.0, hy=0.25, hz=1.0, cfg=cfg)
            scene.add_ground_plane(cfg=newton.ModelBuilder.ShapeConfig(ke=ke, kf=kf, kd=kd, mu=mu))
            self.model = scene.finalize(requires_grad=True)
            self.model.soft_contact_ke = ke
            self.model.soft_contact_kf = kf
            self.model.soft_contact_kd = kd
            self.model.soft_contact_mu = mu
            self.model.soft_contact_restitution = 1.0
            self.solver = newton.solvers.SolverSemiImplicit(self.model)
            self.states = [self.model.state() for _ in range(FRAMES * SUBSTEPS + 1)]
            self.control = self.model.control()
            self.pipeline = newton.CollisionPipeline(self.model, broad_phase="explicit", soft_contact_gap=10.0,
                                                     requires_grad=True)
            self.contacts = self.pipeline.contacts()
            self.pipeline.collide(self.states[0], self.contacts)
            self.loss = wp.zeros(1, dtype=wp.float32, requires_grad=True)

    def forward(self):
        for t in range(FRAMES * SUBSTEPS):
            self.states[t].clear_forces()
            self.solver.step(self.states[t], self.states[t + 1], self.control, self.contacts, self.sim_dt)
        wp.launch(_loss_kernel, dim=1, inputs=[self.states[-1].particle_q, wp.vec3(*TARGET), self.loss],
                  device=self.device)
        return self.loss

    def velocity(self) -> np.ndarray:
        return self.states[0].particle_qd.numpy()[0].astype(np.float64)

    def final_position(self) -> np.ndarray:
        return self.states[-1].particle_q.numpy()[0].astype(np.float64)

    def bounces(self) -> dict[str, int]:
        """Floor and wall bounces of the last forward, from the substeps' velocities: v_z turning
        from down to up below z = 0.5 m is the floor, v_y turning from +y to -y the wall's front
        (penalty contact spreads a bounce over several substeps; each turn counts once)."""
        qd = np.array([s.particle_qd.numpy()[0] for s in self.states], dtype=np.float64)
        q = np.array([s.particle_q.numpy()[0] for s in self.states], dtype=np.float64)
        floor = int(np.sum((qd[:-1, 2] < 0.0) & (qd[1:, 2] >= 0.0) & (q[1:, 2] < 0.5)))
        wall = int(np.sum((qd[:-1, 1] > 0.0) & (qd[1:, 1] <= 0.0)))
        return {"floor": floor, "wall": wall}

    def gradient(self) -> tuple[float, np.ndarray]:
        """(loss, d loss / d initial velocity) by the tape."""
        tape = wp.Tape()
        with tape:
            self.forward()
        tape.backward(self.loss)
        grad = self.states[0].particle_qd.grad.numpy()[0].astype(np.float64).copy()
        loss = float(self.loss.numpy()[0])
        tape.zero()
        return loss, grad

    def check_grad(self, eps: float = 1.0e-3) -> dict:
        """The example's check: central differences (step ``eps``) against the tape."""
        param = self.states[0].particle_qd
        x_c = param.numpy().flatten()
        numeric = np.zeros(3)
        for i in range(3):
            step = np.zeros_like(x_c)
            step[i] = eps
            param.assign(x_c + step)
            l1 = float(self.forward().numpy()[0])
            param.assign(x_c - step)
            l0 = float(self.forward().numpy()[0])
            numeric[i] = (l1 - l0) / (2.0 * eps)
        param.assign(x_c)
        _, analytic = self.gradient()
        return {"analytic": analytic.tolist(), "numeric": numeric.tolist(), "step": eps,
                "relative_error": float(np.linalg.norm(analytic - numeric) / max(np.linalg.norm(numeric), 1e-300))}


def optimise(iters: int, start_velocity=(0.0, 5.0, -5.0), tolerance: float = 0.01) -> dict:
    """The example's training loop (gradient descent, rate 0.02) for ``iters`` iterations; stops
    early once the end point is within ``tolerance`` [m] of the target after bouncing off the
    floor and the wall (the same success as ``scenes.bank_shot``)."""
    ball = NewtonBall(start_velocity)
    t0 = time.perf_counter()
    losses, distances, reached = [], [], None
    for it in range(iters + 1):
        loss, grad = ball.gradient()
        dist = float(np.linalg.norm(ball.final_position() - np.asarray(TARGET)))
        losses.append(loss)
        distances.append(dist)
        hits = ball.bounces()
        if dist < tolerance and hits["floor"] > 0 and hits["wall"] > 0:
            reached = it
            break
        if it == iters:
            break
        ball.states[0].particle_qd.assign((ball.velocity() - TRAIN_RATE * grad)[None].astype(np.float32))
    wall = time.perf_counter() - t0
    return {"reached_target": reached is not None, "iterations_to_target": reached, "final_distance": distances[-1],
            "floor_bounces": hits["floor"], "wall_bounces": hits["wall"],
            "final_loss": losses[-1], "rollouts": len(losses), "wall_time": wall,
            "final_velocity": ball.velocity().tolist(), "loss_curve": losses, "distance_curve": distances}

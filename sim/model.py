"""Static description (:class:`Model`) and time-varying arrays (:class:`State`) of a simulation.

Newton-style split: a :class:`sim.builder.ModelBuilder` collects particles, springs, cloth
triangles, rigid bodies and static colliders, and ``finalize()`` turns them into a read-only
:class:`Model` of Warp arrays (float64 by default). :meth:`Model.state` allocates a
:class:`State`; a stepper maps ``state_in -> state_out`` and never overwrites an array a tape may
have read (one State per substep when differentiating).

Units: SI (m, kg, s, N). Shapes use P particles, S springs, T cloth triangles, B rigid bodies,
and per-body surface meshes flattened into "shape" arrays.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import warp as wp

from sim.collision_mesh import CollisionMesh

COMPONENTS = ("cloth", "rigid", "spheres", "static", "self_collision")
"""What a scene can ask for; the stepper launches only the kernels and collision pairs these need."""


@dataclass
class Model:
    """Static description of a scene (all arrays on ``device``; float arrays float64).

    Attributes:
        device: Warp device ("cpu", "cuda:0", ...).
        components: subset of :data:`COMPONENTS` the scene uses.
        gravity: gravitational acceleration [m/s^2], (3,) numpy.

        particle_count: P.
        particle_q: initial particle positions [m], wp.array(vec3d) (P,).
        particle_qd: initial particle velocities [m/s], wp.array(vec3d) (P,).
        particle_mass: [kg], wp.array(float64) (P,); 0 for pinned particles.
        particle_inv_mass: [1/kg], wp.array(float64) (P,); 0 for pinned particles.

        spring_count: S.
        spring_indices: particle pairs, wp.array(int32) (S, 2).
        spring_rest_length: [m], wp.array(float64) (S,).
        spring_stiffness: [N/m], wp.array(float64) (S,).
        spring_damping: [N s/m], wp.array(float64) (S,) (along the spring).

        tri_count: T.
        tri_indices: cloth triangles (particle indices), wp.array(int32) (T, 3).

        body_count: B.
        body_q: initial poses, wp.array(transformd) (B,): (position of the centre of mass [m],
            orientation quaternion (x, y, z, w)).
        body_qd: initial twists, wp.array(spatial_vectord) (B,): (angular velocity [rad/s],
            linear velocity of the centre of mass [m/s]), both in world frame.
        body_mass: [kg], wp.array(float64) (B,).
        body_inv_mass: wp.array(float64) (B,).
        body_inertia: body-frame inertia tensor about the centre of mass [kg m^2], wp.array(mat33d).
        body_inv_inertia: its inverse, wp.array(mat33d) (B,).

        shape_vertices: rigid-body surface vertices in body frame (relative to the centre of
            mass) [m], wp.array(vec3d) (Vs,); ``shape_vertex_body`` (Vs,) int32 gives the body.
        shape_faces: rigid surface triangles (indices into shape_vertices), wp.array(int32) (Fs, 3).

        sphere_count: number of sphere bodies (Ns).
        sphere_body: the body of each sphere, wp.array(int32) (Ns,).
        sphere_radius: [m], wp.array(float64) (Ns,).

        static_vertices: static collider mesh vertices in world frame [m], wp.array(vec3d) (Vg,).
        static_faces: wp.array(int32) (Fg, 3).
        plane_count: number of static half-space planes.
        planes: (normal (unit), offset) per plane: points x with dot(n, x) >= offset are outside,
            wp.array(vec4d) (plane_count,).

        restitution: coefficient of restitution (0..1) for impulses.
        friction: Coulomb friction coefficient.
        thickness: minimum separation kept by collision response [m] (0 = none).
        particle_drag: linear air drag of the particles [1/s] (>= 0; 0 = none): each moving
            particle feels the force ``-particle_drag * m v``, applied implicitly
            (``v1 = (v0 + dt a) / (1 + dt particle_drag)``, stable at any step).
    """

    device: str = "cpu"
    components: frozenset = field(default_factory=frozenset)
    gravity: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -9.81]))

    particle_count: int = 0
    particle_q: wp.array | None = None
    particle_qd: wp.array | None = None
    particle_mass: wp.array | None = None
    particle_inv_mass: wp.array | None = None

    spring_count: int = 0
    spring_indices: wp.array | None = None
    spring_rest_length: wp.array | None = None
    spring_stiffness: wp.array | None = None
    spring_damping: wp.array | None = None

    tri_count: int = 0
    tri_indices: wp.array | None = None

    body_count: int = 0
    body_q: wp.array | None = None
    body_qd: wp.array | None = None
    body_mass: wp.array | None = None
    body_inv_mass: wp.array | None = None
    body_inertia: wp.array | None = None
    body_inv_inertia: wp.array | None = None

    shape_vertices: wp.array | None = None
    shape_vertex_body: wp.array | None = None
    shape_faces: wp.array | None = None

    sphere_count: int = 0
    sphere_body: wp.array | None = None
    sphere_radius: wp.array | None = None

    static_vertices: wp.array | None = None
    static_faces: wp.array | None = None
    plane_count: int = 0
    planes: wp.array | None = None

    restitution: float = 0.0
    friction: float = 0.5
    thickness: float = 0.0
    particle_drag: float = 0.0
    _collision_mesh: object = field(default=None, init=False, repr=False, compare=False)

    @property
    def collision_mesh(self) -> CollisionMesh:
        """The model's collidable surface (:class:`sim.collision_mesh.CollisionMesh`), built on
        first use and shared by the collision response, the penetration checker and the
        recorder (a scaled copy of the model builds its own)."""
        if self._collision_mesh is None:
            self._collision_mesh = CollisionMesh.from_model(self)
        return self._collision_mesh

    def scaled(self, factor: float) -> Model:
        """The same scene with every length multiplied by ``factor`` (> 0, finite) and the
        masses and times kept: positions, rest lengths, thickness, plane offsets and gravity
        scale by ``factor``, velocities too, inertia tensors by ``factor**2`` (so densities
        scale by ``factor**-2`` per area and ``factor**-3`` per volume); spring stiffness and
        damping [N/m = kg/s^2, N s/m = kg/s] and the particle drag [1/s] are unchanged. The motion of the scaled model is the
        original one scaled, which tests scale invariance (e.g. scenes at 1e-3 and 1e3)."""
        import dataclasses

        f = float(factor)
        if not np.isfinite(f) or f <= 0.0:
            raise ValueError(f"factor must be positive and finite, got {factor!r}")

        def mul(a, k):
            if a is None:
                return None
            if a.dtype == wp.transformd:  # (position, quaternion): only the position scales
                v = a.numpy().copy()
                v[:, :3] *= k
                return wp.array(v, dtype=a.dtype, device=a.device)
            if a.dtype == wp.spatial_vectord:  # (angular, linear): only the linear part scales
                v = a.numpy().copy()
                v[:, 3:] *= k
                return wp.array(v, dtype=a.dtype, device=a.device)
            if a.dtype == wp.vec4d:  # planes (normal, offset)
                v = a.numpy().copy()
                v[:, 3] *= k
                return wp.array(v, dtype=a.dtype, device=a.device)
            return wp.array(a.numpy() * k, dtype=a.dtype, device=a.device)

        return dataclasses.replace(
            self,
            gravity=np.asarray(self.gravity, dtype=np.float64) * f,
            particle_q=mul(self.particle_q, f),
            particle_qd=mul(self.particle_qd, f),
            spring_rest_length=mul(self.spring_rest_length, f),
            body_q=mul(self.body_q, f),
            body_qd=mul(self.body_qd, f),
            body_inertia=mul(self.body_inertia, f * f),
            body_inv_inertia=mul(self.body_inv_inertia, 1.0 / (f * f)),
            shape_vertices=mul(self.shape_vertices, f),
            sphere_radius=mul(self.sphere_radius, f),
            static_vertices=mul(self.static_vertices, f),
            planes=mul(self.planes, f),
            thickness=self.thickness * f,
        )

    def state(self, requires_grad: bool = False) -> State:
        """A new :class:`State` holding copies of the model's initial positions and velocities."""

        def copy(a, dtype):
            if a is None:
                return wp.zeros(0, dtype=dtype, device=self.device, requires_grad=requires_grad)
            return wp.clone(a, requires_grad=requires_grad)

        return State(
            particle_q=copy(self.particle_q, wp.vec3d),
            particle_qd=copy(self.particle_qd, wp.vec3d),
            body_q=copy(self.body_q, wp.transformd),
            body_qd=copy(self.body_qd, wp.spatial_vectord),
        )


@dataclass
class State:
    """Time-varying arrays (float64).

    Attributes:
        particle_q: positions [m], (P,) vec3d.
        particle_qd: velocities [m/s], (P,) vec3d.
        body_q: poses (centre of mass, quaternion xyzw), (B,) transformd.
        body_qd: twists (angular [rad/s], linear [m/s]) in world frame, (B,) spatial_vectord.
    """

    particle_q: wp.array
    particle_qd: wp.array
    body_q: wp.array
    body_qd: wp.array

    def numpy(self) -> dict:
        """Copies of all arrays as numpy (for logging and tests; on the CPU ``wp.array.numpy()``
        is a view of memory a stepper may reuse, so these are real copies)."""
        return {
            "particle_q": self.particle_q.numpy().copy(),
            "particle_qd": self.particle_qd.numpy().copy(),
            "body_q": self.body_q.numpy().copy(),
            "body_qd": self.body_qd.numpy().copy(),
        }

"""Newton-style :class:`ModelBuilder`: add cloth, rigid bodies and static colliders, then
:meth:`ModelBuilder.finalize` into a :class:`sim.model.Model` of float64 Warp arrays.

Every ``add_*`` method validates all of its arguments first and raises a :class:`ValueError` that
names the offending argument before anything is written, so a failed call leaves the builder
unchanged. Units are SI (m, kg, s, N); rotations are unit quaternions ``(x, y, z, w)`` or 3x3
rotation matrices.

Example:
    >>> from sim.builder import ModelBuilder
    >>> from sim.mesh_io import box_mesh
    >>> b = ModelBuilder()
    >>> cloth = b.add_cloth_grid((0, 0, 1), None, 4, 4, 0.25, 0.25, density=0.2,
    ...     stretch_stiffness=1e3, shear_stiffness=1e2, bend_stiffness=10.0, damping=0.1,
    ...     pinned=[0, 4])
    >>> body = b.add_rigid_body(*box_mesh(0.1), density=500.0, pos=(0, 0, 0.5))
    >>> b.add_ground_plane()
    0
    >>> model = b.finalize("cpu")  # doctest: +SKIP
"""

from __future__ import annotations

import numpy as np
import warp as wp

from sim.model import COMPONENTS, Model
from sim.mass_properties import VOLUME_RTOL, check_closed_oriented, lumped_masses, mesh_mass_properties
from sim.validation import (Pinned, Vec3Like, check_nondegenerate, check_rotation, check_scalar, check_triangles,
                            check_vec3, check_velocities, check_vertices, compact_mesh, pinned_mask, sphere_overlap)

__all__ = ["ModelBuilder"]




class ModelBuilder:
    """Collects particles, springs, cloth triangles, rigid bodies and static colliders.

    Args:
        gravity: Gravitational acceleration [m/s^2], (3,) (see :meth:`set_gravity`).

    Attributes (read-only counts): ``particle_count``, ``spring_count``, ``tri_count``,
    ``body_count``, ``plane_count``, ``static_vertex_count``, ``static_face_count``,
    ``components``.
    """

    def __init__(self, gravity: Vec3Like | float = (0.0, 0.0, -9.81)) -> None:
        self._gravity = np.array([0.0, 0.0, -9.81])
        self.set_gravity(gravity)
        self._components: set[str] = set()

        self._particle_q: list[np.ndarray] = []
        self._particle_qd: list[np.ndarray] = []
        self._particle_mass: list[np.ndarray] = []
        self._particle_n = 0

        self._spring_idx: list[np.ndarray] = []
        self._spring_rest: list[np.ndarray] = []
        self._spring_k: list[np.ndarray] = []
        self._spring_d: list[np.ndarray] = []
        self._spring_n = 0

        self._tris: list[np.ndarray] = []
        self._tri_n = 0

        self._body_q: list[np.ndarray] = []  # (7,) p, q(xyzw)
        self._body_qd: list[np.ndarray] = []  # (6,) w, v
        self._body_mass: list[float] = []
        self._body_inertia: list[np.ndarray] = []
        self._shape_v: list[np.ndarray] = []
        self._shape_f: list[np.ndarray] = []
        self._shape_body: list[np.ndarray] = []
        self._shape_vn = 0

        self._sphere_body: list[int] = []
        self._sphere_radius: list[float] = []

        self._static_v: list[np.ndarray] = []
        self._static_f: list[np.ndarray] = []
        self._static_vn = 0
        self._static_mesh_n = 0
        self._planes: list[np.ndarray] = []

        self._restitution = 0.0
        self._friction = 0.5
        self._thickness = 0.0
        self._particle_drag = 0.0

    # ---------------------------------------------------------------- global settings
    def set_gravity(self, g: Vec3Like | float) -> None:
        """Sets gravity [m/s^2]: a (3,) vector, or a scalar taken as its z component (e.g. -9.81)."""
        if np.ndim(g) == 0:
            self._gravity = np.array([0.0, 0.0, check_scalar(g, "g")])
        else:
            self._gravity = check_vec3(g, "g")

    @property
    def gravity(self) -> np.ndarray:
        """Gravitational acceleration [m/s^2], (3,) (copy)."""
        return self._gravity.copy()

    @property
    def restitution(self) -> float:
        """Coefficient of restitution in [0, 1]."""
        return self._restitution

    @restitution.setter
    def restitution(self, value: float) -> None:
        v = check_scalar(value, "restitution", nonnegative=True)
        if v > 1.0:
            raise ValueError(f"restitution must be in [0, 1], got {v}")
        self._restitution = v

    @property
    def friction(self) -> float:
        """Coulomb friction coefficient (>= 0)."""
        return self._friction

    @friction.setter
    def friction(self, value: float) -> None:
        self._friction = check_scalar(value, "friction", nonnegative=True)

    @property
    def thickness(self) -> float:
        """Minimum separation kept by the collision response [m] (>= 0; 0 = none)."""
        return self._thickness

    @property
    def particle_drag(self) -> float:
        """Linear air drag of the particles [1/s] (>= 0; 0 = none, the default): the force
        ``-particle_drag * m v`` on every moving particle (:attr:`sim.model.Model.particle_drag`).
        It lets a draped cloth come to rest: the spring damping acts along the springs only, so
        a flap swinging about a fold keeps swinging without it."""
        return self._particle_drag

    @particle_drag.setter
    def particle_drag(self, value: float) -> None:
        self._particle_drag = check_scalar(value, "particle_drag", nonnegative=True)

    @thickness.setter
    def thickness(self, value: float) -> None:
        self._thickness = check_scalar(value, "thickness", nonnegative=True)

    def set_contact(
        self, *, restitution: float | None = None, friction: float | None = None, thickness: float | None = None
    ) -> None:
        """Sets any of restitution [0..1], friction (>= 0) and thickness [m] (>= 0), all-or-nothing."""
        r = self._restitution if restitution is None else check_scalar(restitution, "restitution", nonnegative=True)
        if r > 1.0:
            raise ValueError(f"restitution must be in [0, 1], got {r}")
        f = self._friction if friction is None else check_scalar(friction, "friction", nonnegative=True)
        h = self._thickness if thickness is None else check_scalar(thickness, "thickness", nonnegative=True)
        self._restitution, self._friction, self._thickness = r, f, h

    def add_component(self, name: str) -> None:
        """Declares a component the scene needs (one of :data:`sim.model.COMPONENTS`)."""
        if name not in COMPONENTS:
            raise ValueError(f"name must be one of {COMPONENTS}, got {name!r}")
        self._components.add(name)

    def enable_self_collision(self) -> None:
        """Asks the stepper for cloth self-collision (adds the ``"self_collision"`` component)."""
        self._components.add("self_collision")

    # ---------------------------------------------------------------- counts
    @property
    def components(self) -> frozenset:
        """Components added so far (subset of :data:`sim.model.COMPONENTS`)."""
        return frozenset(self._components)

    @property
    def particle_count(self) -> int:
        """P: particles added so far."""
        return self._particle_n

    @property
    def spring_count(self) -> int:
        """S: springs added so far."""
        return self._spring_n

    @property
    def tri_count(self) -> int:
        """T: cloth triangles added so far."""
        return self._tri_n

    @property
    def body_count(self) -> int:
        """B: rigid bodies added so far."""
        return len(self._body_mass)

    @property
    def plane_count(self) -> int:
        """Static half-space planes added so far."""
        return len(self._planes)

    @property
    def static_vertex_count(self) -> int:
        """Vertices of all static meshes (after dropping unused ones)."""
        return self._static_vn

    @property
    def static_face_count(self) -> int:
        """Triangles of all static meshes."""
        return sum(len(f) for f in self._static_f)

    # ---------------------------------------------------------------- particles / cloth
    def _commit_particles(self, q, qd, mass, springs=None, rest=None, k=None, d=None, tris=None) -> range:
        """Appends already-validated particle data (local indices offset here)."""
        start = self._particle_n
        self._particle_q.append(q)
        self._particle_qd.append(qd)
        self._particle_mass.append(mass)
        self._particle_n += len(q)
        if springs is not None and len(springs):
            self._spring_idx.append(springs + start)
            self._spring_rest.append(rest)
            self._spring_k.append(k)
            self._spring_d.append(d)
            self._spring_n += len(springs)
        if tris is not None and len(tris):
            self._tris.append(tris + start)
            self._tri_n += len(tris)
        self._components.add("cloth")
        return range(start, self._particle_n)

    def add_particle(
        self, pos: Vec3Like, velocity: Vec3Like = (0.0, 0.0, 0.0), mass: float = 1.0, *, pinned: bool = False
    ) -> int:
        """Adds one free particle (simulated with the cloth; adds the ``"cloth"`` component).

        Args:
            pos: Position [m], (3,).
            velocity: Velocity [m/s], (3,).
            mass: [kg], > 0 (a pinned particle stores 0 regardless).
            pinned: Kinematic particle (mass and inverse mass 0).

        Returns:
            The particle's index.
        """
        p = check_vec3(pos, "pos")
        v = check_vec3(velocity, "velocity")
        m = check_scalar(mass, "mass", positive=True)
        r = self._commit_particles(p[None], v[None], np.array([0.0 if pinned else m]))
        return r.start

    @staticmethod
    def _springs(q: np.ndarray, pairs: np.ndarray, k: float, d: float, what: str):
        rest = np.linalg.norm(q[pairs[:, 1]] - q[pairs[:, 0]], axis=1)
        bad = np.flatnonzero(rest <= 0.0)
        if bad.size:
            raise ValueError(f"{what} spring between coincident particles {pairs[bad[0]].tolist()}")
        return rest, np.full(len(pairs), k), np.full(len(pairs), d)

    def add_cloth_grid(
        self,
        pos: Vec3Like,
        rot,
        dim_x: int,
        dim_y: int,
        cell_x: float,
        cell_y: float,
        *,
        density: float,
        stretch_stiffness: float,
        shear_stiffness: float,
        bend_stiffness: float,
        damping: float,
        velocity: Vec3Like | np.ndarray = (0.0, 0.0, 0.0),
        pinned: Pinned = (),
    ) -> range:
        """Adds a rectangular cloth of ``dim_x x dim_y`` cells in its local x-y plane.

        Particle ``(i, j)`` (``0 <= i <= dim_x``, ``0 <= j <= dim_y``) has local index
        ``j * (dim_x + 1) + i`` and world position ``pos + R @ (i * cell_x, j * cell_y, 0)``
        (so ``pos`` is the corner of particle 0). Cell ``(i, j)`` is split along its
        ``(i, j)-(i+1, j+1)`` diagonal into two triangles wound counter-clockwise about local +z.

        Springs (in this order): stretch along every grid edge, ``dim_x (dim_y + 1) + dim_y (dim_x
        + 1)``; shear on both diagonals of every cell, ``2 dim_x dim_y``; bending between
        distance-2 neighbours along rows and columns, ``(dim_x - 1)(dim_y + 1) + (dim_y - 1)(dim_x
        + 1)`` (none along an axis with a single cell). Rest lengths are the initial distances.

        Args:
            pos: Position of particle 0 [m], (3,).
            rot: Orientation: quaternion ``(x, y, z, w)``, 3x3 rotation matrix or None (identity).
            dim_x: Cells along local x (>= 1).
            dim_y: Cells along local y (>= 1).
            cell_x: Cell size along x [m] (> 0).
            cell_y: Cell size along y [m] (> 0).
            density: Areal density [kg/m^2] (> 0); each triangle gives area/3 of its mass to each
                corner.
            stretch_stiffness: [N/m] (>= 0).
            shear_stiffness: [N/m] (>= 0).
            bend_stiffness: [N/m] (>= 0).
            damping: Damping of every spring along its axis [N s/m] (>= 0).
            velocity: Initial velocity [m/s], (3,) for all particles or (P, 3) per particle.
            pinned: Local indices (or a boolean mask (P,), or ``pinned(index, world_pos) -> bool``)
                of kinematic particles: mass and inverse mass 0.

        Returns:
            Global indices of the new particles.
        """
        nx = self._int(dim_x, "dim_x")
        ny = self._int(dim_y, "dim_y")
        cx = check_scalar(cell_x, "cell_x", positive=True)
        cy = check_scalar(cell_y, "cell_y", positive=True)
        p0 = check_vec3(pos, "pos")
        r, _ = check_rotation(rot)
        rho = check_scalar(density, "density", positive=True)
        ks = check_scalar(stretch_stiffness, "stretch_stiffness", nonnegative=True)
        kh = check_scalar(shear_stiffness, "shear_stiffness", nonnegative=True)
        kb = check_scalar(bend_stiffness, "bend_stiffness", nonnegative=True)
        kd = check_scalar(damping, "damping", nonnegative=True)

        i, j = np.meshgrid(np.arange(nx + 1), np.arange(ny + 1))  # (ny+1, nx+1), row j
        local = np.stack([i * cx, j * cy, np.zeros_like(i, dtype=np.float64)], axis=-1).reshape(-1, 3)
        q = p0 + local @ r.T
        n = len(q)
        qd = check_velocities(velocity, n, "velocity")
        mask = pinned_mask(pinned, q)

        idx = np.arange(n).reshape(ny + 1, nx + 1)
        c00, c10, c01, c11 = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
        tris = np.concatenate(
            [np.stack([c00, c10, c11], -1).reshape(-1, 3), np.stack([c00, c11, c01], -1).reshape(-1, 3)]
        )
        # interleave so the two triangles of a cell are consecutive: cell-major order
        tris = tris.reshape(2, -1, 3).transpose(1, 0, 2).reshape(-1, 3)

        def pairs(a, b):
            return np.stack([a.reshape(-1), b.reshape(-1)], axis=1)

        stretch = np.concatenate([pairs(idx[:, :-1], idx[:, 1:]), pairs(idx[:-1, :], idx[1:, :])])
        shear = np.concatenate([pairs(c00, c11), pairs(c10, c01)])
        bend = np.concatenate([pairs(idx[:, :-2], idx[:, 2:]), pairs(idx[:-2, :], idx[2:, :])])

        area2 = np.linalg.norm(np.cross(q[tris[:, 1]] - q[tris[:, 0]], q[tris[:, 2]] - q[tris[:, 0]]), axis=1)
        mass = lumped_masses(q, tris, area2, rho)
        mass[mask] = 0.0

        springs, rests, ks_, kd_ = [], [], [], []
        for prs, k, what in ((stretch, ks, "stretch"), (shear, kh, "shear"), (bend, kb, "bending")):
            if len(prs):
                rest, kk, dd = self._springs(q, prs, k, kd, what)
                springs.append(prs), rests.append(rest), ks_.append(kk), kd_.append(dd)
        return self._commit_particles(
            q, qd, mass,
            np.concatenate(springs).astype(np.int64), np.concatenate(rests),
            np.concatenate(ks_), np.concatenate(kd_), tris,
        )  # fmt: skip

    def add_cloth_mesh(
        self,
        vertices: np.ndarray,
        triangles: np.ndarray,
        *,
        density: float,
        stretch_stiffness: float,
        bend_stiffness: float,
        damping: float,
        velocity: Vec3Like | np.ndarray = (0.0, 0.0, 0.0),
        pinned: Pinned = (),
        pos: Vec3Like = (0.0, 0.0, 0.0),
        rot=None,
    ) -> range:
        """Adds a cloth from a triangle mesh: one particle per vertex.

        Springs: stretch on every unique edge (sorted by ``(min, max)`` vertex index), then
        bending across every interior edge, between the two vertices opposite it (deduplicated).
        Edges shared by more than two triangles are rejected (bending would be ambiguous).

        Args:
            vertices: Rest positions [m], float (N, 3), in the mesh frame; world positions are
                ``pos + R @ v``.
            triangles: Vertex indices, int (T, 3); every vertex must be used (a vertex without
                triangles would have no mass).
            density: Areal density [kg/m^2] (> 0); area/3 of each triangle to each corner.
            stretch_stiffness: [N/m] (>= 0).
            bend_stiffness: [N/m] (>= 0).
            damping: Damping of every spring along its axis [N s/m] (>= 0).
            velocity: Initial velocity [m/s], (3,) or (N, 3).
            pinned: Local vertex indices, a boolean mask (N,) or ``pinned(index, world_pos) ->
                bool``; pinned particles get mass and inverse mass 0.
            pos: Translation [m], (3,).
            rot: Quaternion ``(x, y, z, w)``, 3x3 rotation matrix or None (identity).

        Returns:
            Global indices of the new particles (in vertex order).
        """
        v = check_vertices(vertices, "vertices")
        t = check_triangles(triangles, len(v), "triangles")
        rho = check_scalar(density, "density", positive=True)
        ks = check_scalar(stretch_stiffness, "stretch_stiffness", nonnegative=True)
        kb = check_scalar(bend_stiffness, "bend_stiffness", nonnegative=True)
        kd = check_scalar(damping, "damping", nonnegative=True)
        p0 = check_vec3(pos, "pos")
        r, _ = check_rotation(rot)
        n = len(v)
        qd = check_velocities(velocity, n, "velocity")
        area2 = check_nondegenerate(v, t, "triangles")
        used = np.zeros(n, dtype=bool)
        used[t.reshape(-1)] = True
        if not used.all():
            raise ValueError(
                f"vertices: {int((~used).sum())} vertex/vertices (first {int(np.argmin(used))}) belong to "
                "no triangle and would have no mass"
            )
        st = np.sort(t, axis=1)
        _, tcount = np.unique(st, axis=0, return_counts=True)
        if np.any(tcount > 1):
            raise ValueError("triangles contains duplicate triangles (same three vertices)")

        # half-edges: edge k of triangle f is (t[f,k], t[f,k+1]); its opposite vertex t[f,k+2]
        he = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
        opp = np.concatenate([t[:, 2], t[:, 0], t[:, 1]])
        he = np.sort(he, axis=1)
        key = he[:, 0] * n + he[:, 1]
        order = np.argsort(key, kind="stable")
        key_s, opp_s = key[order], opp[order]
        uniq, first, counts = np.unique(key_s, return_index=True, return_counts=True)
        if np.any(counts > 2):
            k = uniq[np.argmax(counts > 2)]
            raise ValueError(
                f"triangles: edge ({k // n}, {k % n}) is shared by {counts.max()} triangles (non-manifold cloth)"
            )
        stretch = np.stack([uniq // n, uniq % n], axis=1)
        interior = first[counts == 2]
        bend = np.sort(np.stack([opp_s[interior], opp_s[interior + 1]], axis=1), axis=1)
        if len(bend):
            bend = np.unique(bend, axis=0)

        q = p0 + v @ r.T
        mask = pinned_mask(pinned, q)
        mass = lumped_masses(q, t, area2, rho)
        mass[mask] = 0.0
        rest_s, k_s, d_s = self._springs(q, stretch, ks, kd, "stretch")
        springs, rests, kk, dd = [stretch], [rest_s], [k_s], [d_s]
        if len(bend):
            rest_b, k_b, d_b = self._springs(q, bend, kb, kd, "bending")
            springs.append(bend), rests.append(rest_b), kk.append(k_b), dd.append(d_b)
        return self._commit_particles(
            q, qd, mass, np.concatenate(springs), np.concatenate(rests), np.concatenate(kk), np.concatenate(dd), t
        )

    # ---------------------------------------------------------------- rigid bodies
    def add_rigid_body(
        self,
        vertices: np.ndarray,
        triangles: np.ndarray,
        *,
        density: float,
        pos: Vec3Like = (0.0, 0.0, 0.0),
        rot=None,
        velocity: Vec3Like = (0.0, 0.0, 0.0),
        angular_velocity: Vec3Like = (0.0, 0.0, 0.0),
    ) -> int:
        """Adds a homogeneous rigid body bounded by a closed, outward-oriented triangle mesh.

        Mass, centre of mass ``c`` and inertia come from :func:`mesh_mass_properties`. The body
        frame has the mesh's axes and its origin at ``c``: the stored surface vertices are
        ``v - c`` and the inertia tensor is about ``c`` in mesh axes (not diagonalised). The mesh
        frame is placed at ``pos`` with orientation ``rot``, so ``body_q = (pos + R c, rot)``.
        Vertices not used by any triangle are dropped.

        Args:
            vertices: Surface vertices in the mesh frame [m], float (N, 3).
            triangles: Closed, 2-manifold, consistently outward (counter-clockwise seen from
                outside) triangles, int (T, 3).
            density: [kg/m^3] (> 0).
            pos: World position of the mesh frame's origin [m], (3,).
            rot: Quaternion ``(x, y, z, w)``, 3x3 rotation matrix or None (identity).
            velocity: World linear velocity of the centre of mass [m/s], (3,).
            angular_velocity: World angular velocity [rad/s], (3,).

        Returns:
            The body index.

        Raises:
            ValueError: Bad shapes, NaN/inf, bad indices, degenerate triangles, an open,
                non-manifold or inconsistently oriented mesh, an inverted (negative volume) or
                flat mesh, non-positive density, an invalid rotation.
        """
        rho = check_scalar(density, "density", positive=True)
        p0 = check_vec3(pos, "pos")
        r, quat = check_rotation(rot)
        lin = check_vec3(velocity, "velocity")
        ang = check_vec3(angular_velocity, "angular_velocity")
        v = check_vertices(vertices, "vertices", min_count=4)
        t = check_triangles(triangles, len(v), "triangles")
        v, t = compact_mesh(v, t)
        check_nondegenerate(v, t, "triangles")
        check_closed_oriented(t, len(v), "triangles")
        props = mesh_mass_properties(v, t, rho)
        diag = np.linalg.norm(v.max(axis=0) - v.min(axis=0))
        if abs(props.volume) <= VOLUME_RTOL * diag**3:
            raise ValueError(f"vertices/triangles enclose zero volume ({props.volume:.3g} m^3)")
        if props.volume < 0.0:
            raise ValueError(
                f"triangles are inverted (inward-facing normals, volume {props.volume:.6g} m^3); "
                "reverse the winding, e.g. triangles[:, ::-1]"
            )
        inertia = 0.5 * (props.inertia + props.inertia.T)
        if np.any(np.linalg.eigvalsh(inertia) <= 0.0):
            raise ValueError("vertices/triangles give a non-positive-definite inertia tensor")

        body = len(self._body_mass)
        self._body_q.append(np.concatenate([p0 + r @ props.com, quat]))
        self._body_qd.append(np.concatenate([ang, lin]))
        self._body_mass.append(props.mass)
        self._body_inertia.append(inertia)
        self._shape_f.append(t + self._shape_vn)
        self._shape_v.append(v - props.com)
        self._shape_body.append(np.full(len(v), body, dtype=np.int32))
        self._shape_vn += len(v)
        self._components.add("rigid")
        return body

    def add_sphere(
        self,
        radius: float,
        *,
        density: float | None = None,
        mass: float | None = None,
        pos: Vec3Like = (0.0, 0.0, 0.0),
        rot=None,
        velocity: Vec3Like = (0.0, 0.0, 0.0),
        angular_velocity: Vec3Like = (0.0, 0.0, 0.0),
    ) -> int:
        """Adds a homogeneous solid sphere: a rigid body with the exact inertia ``2/5 m r^2``.

        Spheres collide with each other, the ground planes and static meshes (:mod:`kernels.spheres`);
        a model with spheres has no cloth or rigid meshes (:meth:`finalize` says so).

        Args:
            radius: [m] (> 0).
            density: [kg/m^3] (> 0); give it or ``mass``, not both.
            mass: [kg] (> 0).
            pos: World position of the centre [m], (3,).
            rot: Quaternion ``(x, y, z, w)``, 3x3 rotation matrix or None (identity).
            velocity: World linear velocity [m/s], (3,).
            angular_velocity: World angular velocity [rad/s], (3,).

        Returns:
            The body index (spheres and rigid bodies share the body numbering).
        """
        r = check_scalar(radius, "radius", positive=True)
        if (density is None) == (mass is None):
            raise ValueError("add_sphere needs exactly one of density [kg/m^3] and mass [kg]")
        volume = 4.0 / 3.0 * np.pi * r**3
        given = "mass" if mass is not None else "density"
        m = (check_scalar(mass, "mass", positive=True) if mass is not None
             else check_scalar(density, "density", positive=True) * volume)
        inertia = 0.4 * m * r * r
        if not (np.isfinite(m) and m > 0.0 and np.isfinite(1.0 / m) and inertia > 0.0 and np.isfinite(1.0 / inertia)):
            raise ValueError(f"radius {r!r} m and {given} {mass if mass is not None else density!r} give a mass "
                             f"({m!r} kg) or moment of inertia ({inertia!r} kg m^2) whose inverse is not finite")
        p0 = check_vec3(pos, "pos")
        _, quat = check_rotation(rot)
        lin = check_vec3(velocity, "velocity")
        ang = check_vec3(angular_velocity, "angular_velocity")
        body = len(self._body_mass)
        self._body_q.append(np.concatenate([p0, quat]))
        self._body_qd.append(np.concatenate([ang, lin]))
        self._body_mass.append(m)
        self._body_inertia.append(np.eye(3) * inertia)
        self._sphere_body.append(body)
        self._sphere_radius.append(r)
        self._components.add("spheres")
        return body

    def _check_spheres(self) -> None:
        """Spheres neither overlap (beyond rounding: touching is fine) nor share a model with
        meshes."""
        if not self._sphere_body:
            return
        others = [what for what, n in (("cloth or particles", self._particle_n), ("rigid meshes", self._shape_vn)) if n]
        if others:
            raise ValueError(f"spheres collide with each other, ground planes and static meshes only; this model also "
                             f"has {' and '.join(others)} (build them in separate models)")
        problem = sphere_overlap(np.asarray(self._body_q, dtype=np.float64)[self._sphere_body, :3],
                                 np.asarray(self._sphere_radius), self._sphere_body)
        if problem:
            raise ValueError(problem)

    # ---------------------------------------------------------------- static colliders
    def add_static_mesh(
        self, vertices: np.ndarray, triangles: np.ndarray, *, pos: Vec3Like = (0.0, 0.0, 0.0), rot=None
    ) -> int:
        """Adds a static (immovable) triangle mesh collider; open meshes are fine.

        Args:
            vertices: [m], float (N, 3), mesh frame; world = ``pos + R @ v``. Unused vertices
                are dropped.
            triangles: int (T, 3).
            pos: Translation [m], (3,).
            rot: Quaternion ``(x, y, z, w)``, 3x3 rotation matrix or None (identity).

        Returns:
            The static mesh's index (in order of addition).
        """
        v = check_vertices(vertices, "vertices")
        t = check_triangles(triangles, len(v), "triangles")
        p0 = check_vec3(pos, "pos")
        r, _ = check_rotation(rot)
        v, t = compact_mesh(v, t)
        check_nondegenerate(v, t, "triangles")
        self._static_v.append(p0 + v @ r.T)
        self._static_f.append(t + self._static_vn)
        self._static_vn += len(v)
        self._static_mesh_n += 1
        self._components.add("static")
        return self._static_mesh_n - 1

    def add_ground_plane(self, normal: Vec3Like = (0.0, 0.0, 1.0), offset: float = 0.0) -> int:
        """Adds a static half-space ``dot(n, x) >= offset`` (outside) as a plane only (no mesh).

        Args:
            normal: Outward normal, (3,), non-zero (normalised here; ``offset`` is taken w.r.t.
                the unit normal).
            offset: Signed distance of the plane from the origin along the unit normal [m].

        Returns:
            The plane's index.
        """
        n = check_vec3(normal, "normal")
        length = np.linalg.norm(n)
        if not length > 0.0:
            raise ValueError("normal must be non-zero")
        d = check_scalar(offset, "offset")
        self._planes.append(np.concatenate([n / length, [d]]))
        self._components.add("static")
        return len(self._planes) - 1

    # ---------------------------------------------------------------- finalize
    @staticmethod
    def _int(x, name: str, minimum: int = 1) -> int:
        if isinstance(x, bool) or not isinstance(x, (int, np.integer)):
            raise ValueError(f"{name} must be an integer, got {x!r}")
        if x < minimum:
            raise ValueError(f"{name} must be >= {minimum}, got {x}")
        return int(x)

    def finalize(self, device: str = "cpu", requires_grad: bool = False) -> Model:
        """Builds the :class:`Model` (float64 Warp arrays on ``device``); the builder is unchanged.

        Empty categories give zero-length arrays (never None). ``requires_grad`` is set on the
        float arrays (positions, velocities, masses, spring parameters, body poses/twists).

        Args:
            device: Warp device, e.g. ``"cpu"`` or ``"cuda:0"``.
            requires_grad: Allocate gradients for the float arrays.

        Returns:
            The model.
        """
        from core.device import init_warp  # the project's shared, quiet wp.init()

        init_warp()

        def cat(chunks, shape, dtype=np.float64):
            return np.concatenate(chunks).astype(dtype) if chunks else np.zeros(shape, dtype=dtype)

        def arr(a, dtype, grad=False):
            return wp.array(a, dtype=dtype, device=device, requires_grad=grad and requires_grad)

        self._check_spheres()
        mass = cat(self._particle_mass, (0,))
        inv_mass = np.divide(1.0, mass, out=np.zeros_like(mass), where=mass > 0.0)
        body_mass = np.asarray(self._body_mass, dtype=np.float64)
        body_inertia = np.asarray(self._body_inertia, dtype=np.float64).reshape(-1, 3, 3)
        body_inv_inertia = np.linalg.inv(body_inertia) if len(body_inertia) else body_inertia.copy()
        body_inv_inertia = 0.5 * (body_inv_inertia + body_inv_inertia.transpose(0, 2, 1))

        model = Model(
            device=str(device),
            components=frozenset(self._components),
            gravity=self._gravity.copy(),
            particle_count=self._particle_n,
            particle_q=arr(cat(self._particle_q, (0, 3)), wp.vec3d, True),
            particle_qd=arr(cat(self._particle_qd, (0, 3)), wp.vec3d, True),
            particle_mass=arr(mass, wp.float64, True),
            particle_inv_mass=arr(inv_mass, wp.float64, True),
            spring_count=self._spring_n,
            spring_indices=arr(cat(self._spring_idx, (0, 2), np.int32), wp.int32),
            spring_rest_length=arr(cat(self._spring_rest, (0,)), wp.float64, True),
            spring_stiffness=arr(cat(self._spring_k, (0,)), wp.float64, True),
            spring_damping=arr(cat(self._spring_d, (0,)), wp.float64, True),
            tri_count=self._tri_n,
            tri_indices=arr(cat(self._tris, (0, 3), np.int32), wp.int32),
            body_count=len(self._body_mass),
            body_q=arr(np.asarray(self._body_q, dtype=np.float64).reshape(-1, 7), wp.transformd, True),
            body_qd=arr(np.asarray(self._body_qd, dtype=np.float64).reshape(-1, 6), wp.spatial_vectord, True),
            body_mass=arr(body_mass, wp.float64, True),
            body_inv_mass=arr(1.0 / body_mass if len(body_mass) else body_mass, wp.float64, True),
            body_inertia=arr(body_inertia, wp.mat33d, True),
            body_inv_inertia=arr(body_inv_inertia, wp.mat33d, True),
            shape_vertices=arr(cat(self._shape_v, (0, 3)), wp.vec3d),
            shape_vertex_body=arr(cat(self._shape_body, (0,), np.int32), wp.int32),
            shape_faces=arr(cat(self._shape_f, (0, 3), np.int32), wp.int32),
            static_vertices=arr(cat(self._static_v, (0, 3)), wp.vec3d),
            static_faces=arr(cat(self._static_f, (0, 3), np.int32), wp.int32),
            sphere_count=len(self._sphere_body),
            sphere_body=arr(np.asarray(self._sphere_body, dtype=np.int32), wp.int32),
            sphere_radius=arr(np.asarray(self._sphere_radius, dtype=np.float64), wp.float64),
            plane_count=len(self._planes),
            planes=arr(np.asarray(self._planes, dtype=np.float64).reshape(-1, 4), wp.vec4d),
            restitution=self._restitution,
            friction=self._friction,
            thickness=self._thickness,
            particle_drag=self._particle_drag,
        )
        from sim.penetration import warn_initial_penetrations

        warn_initial_penetrations(model)
        return model

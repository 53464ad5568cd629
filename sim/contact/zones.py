"""Impact zones of the fail-safe (Provot 1997; Bridson et al. 2002): which particles and bodies
move as one rigid body, decided on the host from the approaching hits (a union-find)."""

from __future__ import annotations

import numpy as np

from kernels.pose import VERTEX_BODY, VERTEX_PARTICLE


class ImpactZones:
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
        nodes = np.where(vertex_type == VERTEX_PARTICLE, vertex_owner,
                         np.where(vertex_type == VERTEX_BODY, self.P + vertex_owner, self.world))
        pinned = np.isin(vertex_owner, self.pinned) & (vertex_type == VERTEX_PARTICLE)
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
        """The zones as ints for the taped replay (:meth:`sim.contact.replay.ContactReplay.zone_velocities`):
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

"""What one call of the collision response touched (:class:`ContactRecord`), for the handler's
``last_*`` statistics."""

from __future__ import annotations

import numpy as np

from core.buffers import host
from kernels.pose import VERTEX_BODY, VERTEX_PARTICLE


class ContactRecord:
    """The contacts of one handler call, for its ``last_*`` statistics, worked out when first
    read: the recorder, the implicit integrator and the benchmarks read them, a plain stepping
    loop does not.

    Args:
        cs: the call's contact set: a device :class:`sim.contact.contacts.Contacts` (read where it
            is until :meth:`materialize` copies it: the handler calls that before the next call
            reuses the buffers), or None.
        x0, x1: device arrays of the vertices' positions (V + 1, 3) at the start and the
            planned end [m].
        h: the substep [s].
        vertex_type: (V + 1,) the vertex kinds.
    """

    def __init__(self, cs=None, x0=None, x1=None, h=1.0, vertex_type=None) -> None:
        self._h, self._vertex_type = h, vertex_type
        self._device = None
        self._rows = None  # host (kind, vertex indices, weights, normals, toi, normal impulse), x0, x1
        if cs is not None and cs.count:
            self._device = (cs, cs.count, x0, x1)
        self._count = None
        self._contacts = None
        self._body_particles = None

    @property
    def reads_buffers(self) -> bool:
        """Whether the record still reads the handler's device buffers."""
        return self._device is not None

    def materialize(self) -> None:
        """Copies what the record reads out of the handler's buffers (before they are reused)."""
        if self._device is None:
            return
        cs, count, x0, x1 = self._device
        self._device = None
        rows = tuple(np.array(host(getattr(cs, name))[:count])
                     for name in ("kind", "vertices", "weights", "normals", "toi", "normal_impulse"))
        active = rows[5] > 0
        self._rows = (rows, np.array(host(x0)) if active.any() else None, np.array(host(x1)) if active.any() else None)

    def _host_rows(self):
        self.materialize()
        return self._rows

    @property
    def count(self) -> int:
        """How many contacts received an impulse."""
        if self._count is None:
            if self._device is not None:  # the impulses only (no copy of the rest)
                cs, count = self._device[:2]
                self._count = int(np.count_nonzero(host(cs.normal_impulse)[:count] > 0))
            else:
                self._count = 0 if self._rows is None else int(np.count_nonzero(self._rows[0][5] > 0))
        return self._count

    def contacts(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(points (C, 3) [m]: side A's closest point at ``t*`` on the straight paths x0 -> x1,
        normals (C, 3), times of impact (C,) [s]) of the contacts that received an impulse."""
        if self._contacts is None:
            self._contacts = (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
            if self.count:
                (kind, idx, w, n, toi, jn), x0, x1 = self._host_rows()
                active = jn > 0
                ia = idx[active]
                side_a = np.abs(np.where(np.arange(4) < np.where(kind[active] == 1, 2, 1)[:, None], w[active], 0.0))
                y = x0[ia] + (toi[active] / self._h)[:, None, None] * (x1[ia] - x0[ia])
                self._contacts = (np.einsum("ck,ckd->cd", side_a, y), n[active], toi[active])
        return self._contacts

    def body_particles(self) -> np.ndarray:
        """(K,) int64 the particles (sorted, distinct) that share a contact with a rigid body's
        vertex."""
        if self._body_particles is None:
            self._body_particles = np.zeros(0, dtype=np.int64)
            rows = self._host_rows()
            if rows is not None:
                idx = rows[0][1].astype(np.int64)
                types = self._vertex_type[idx]
                touch = (types == VERTEX_BODY).any(axis=1)
                if touch.any():
                    self._body_particles = np.unique(idx[touch][types[touch] == VERTEX_PARTICLE])
        return self._body_particles


NO_CONTACTS = ContactRecord()
"""The record of a call without contacts (shared: a record is not changed after it is made)."""

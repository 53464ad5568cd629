"""Device buffers of the collision response's decisions: :class:`Contacts` (a substep's contact
set, fixed capacity and a count) and :class:`Hits` (one detection pass's hits in canonical
order), filled and read by the kernels of :mod:`kernels.contact_set` without a per-contact
array crossing to the host (the host keeps only counts).

Both grow when a count would pass their capacity (the host checks the count before the kernel
that writes: no write past the end), keeping their rows; once a run's largest sizes have been
met, nothing is allocated.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from core.buffers import grown_capacity, host, zero


class ContactLimitExceeded(RuntimeError):
    """A substep's contacts went past a named limit (hits per collision vertex, or unknowns of
    the exact impulse solve): the substep is far too long for the motion."""

_CONTACT_FIELDS = (("kind", wp.int32), ("pair", wp.vec2i), ("vertices", wp.vec4i), ("toi", wp.float64),
                   ("weights", wp.vec4d), ("normals", wp.vec3d), ("targets", wp.float64), ("timed", wp.int32),
                   ("collided", wp.int32), ("normal_impulse", wp.float64), ("friction_impulse", wp.vec3d))

_HIT_FIELDS = (("kind", wp.int32), ("pair", wp.vec2i), ("vertices", wp.vec4i), ("detected", wp.float64),
               ("source", wp.int32), ("plane", wp.int32), ("row", wp.int32), ("toi", wp.float64),
               ("weights", wp.vec4d), ("normals", wp.vec3d), ("targets", wp.float64), ("approaching", wp.int32),
               ("source_row", wp.int32))


class _Rows:
    """Named device arrays of a common row count (``fields``: (name, dtype) pairs) that grow."""

    FIELDS: tuple = ()

    def __init__(self, device, capacity: int = 64) -> None:
        self.device = wp.get_device(device)
        self.capacity = 0
        self.count = 0
        self.reserve(capacity)

    def _sizes(self, capacity: int) -> dict:
        return {name: capacity for name, _ in self.FIELDS}

    fresh = True  # whether count is the device's count (see Contacts)

    @property
    def rows_bound(self) -> int:
        """A host bound on the rows held: :attr:`count`, or the capacity while the count is on
        the device only (``fresh`` False)."""
        return self.count if self.fresh else self.capacity

    def reserve(self, rows: int) -> None:
        """At least ``rows`` rows of room, the first :attr:`count` rows kept (every row, while the
        count is on the device only: ``fresh`` False)."""
        if rows <= self.capacity:
            return
        capacity = grown_capacity(rows, self.capacity, 64)
        kept = self.rows_bound
        for (name, dtype), size in zip(self.FIELDS, self._sizes(capacity).values()):
            new = wp.zeros(size, dtype=dtype, device=self.device)
            old = getattr(self, name, None)
            if old is not None and kept:
                wp.copy(new, old, count=min(kept, old.shape[0]))
            setattr(self, name, new)
        self.capacity = capacity

    def host(self, name: str) -> np.ndarray:
        """A host copy of the first :attr:`count` rows of array ``name``."""
        return np.array(host(getattr(self, name))[: self.count])


class Contacts(_Rows):
    """A substep's contact set on the device (grown by :func:`kernels.contact_set.add_contacts_kernel`).

    Rows ``0 .. count - 1`` of: ``kind`` (0 vertex-face, 1 edge-edge, 2 vertex-plane), ``pair``
    (``(vertex, face)``, ``(edge, edge)``, ``(vertex, plane)``), ``vertices`` (vec4i, the CCD
    order; vertex-plane: the vertex and the dummy static vertex), ``toi`` (time of impact in the
    substep [s]), ``weights`` (vec4: side A positive, summing to 1, side B negative, summing to
    -1), ``normals`` (unit, side B to side A), ``targets`` (least normal relative velocity after
    the impulses [m/s]), ``timed`` (the time comes from a root or a plane crossing, so the replay
    differentiates it), ``collided`` (an approaching CCD hit reached the row in this substep: its
    primitives meet within the substep unless the impulses stop them), ``normal_impulse`` and
    ``friction_impulse`` (accumulated [N s]).
    ``counter`` holds the row count on the device (the kernels that read or grow the set read
    and write it there); ``count`` is the host's copy, current while ``fresh`` (a growth whose
    count stayed on the device makes it stale until the next read).
    """

    FIELDS = _CONTACT_FIELDS

    def __init__(self, device, capacity: int = 64) -> None:
        super().__init__(device, capacity)
        self.counter = wp.zeros(1, dtype=wp.int32, device=self.device)
        self.fresh = True

    def clear(self) -> None:
        self.count = 0
        self.fresh = True
        zero(self.counter)

    def __len__(self) -> int:
        return self.count


class Hits(_Rows):
    """One detection pass's hits in canonical order (:mod:`kernels.contact_set`), with their
    geometry (``toi`` [s], ``weights``, ``normals``, ``targets``: the replay's definition,
    :func:`kernels.contact_geometry.contact_geometry_kernel`) and decisions (``row``: the pair's row in
    the contact set or -1; ``approaching``: 0 / 1; ``source_row``: the set's row the hit
    went to). ``keys`` / ``order`` hold the sort (twice the capacity: Warp's radix sort needs
    the room)."""

    FIELDS = _HIT_FIELDS + (("keys", wp.int64), ("order", wp.int32))

    def _sizes(self, capacity: int) -> dict:
        sizes = super()._sizes(capacity)
        sizes["keys"] = sizes["order"] = 2 * capacity
        return sizes

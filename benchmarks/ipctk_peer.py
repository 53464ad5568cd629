"""ipctk (IPC Toolkit 1.6.1, PyPI) as the CCD peer: Tight Inclusion CCD called once per query.

What ipctk 1.6.1 exposes (found with help(); there is NO top-level ``ipctk.point_triangle_ccd`` /
``ipctk.edge_edge_ccd`` in this version):

* ``ipctk.tight_inclusion.point_triangle_ccd(v_t0, f0_t0, f1_t0, f2_t0, v_t1, f0_t1, f1_t1, f2_t1,
  min_distance=0, tmax=1, tolerance=1e-6, max_iterations=10_000_000, filter=[-1, -1, -1],
  no_zero_toi=False, ccd_method=CCDRootFindingMethod.BREADTH_FIRST_SEARCH) -> (hit, toi, precision)``
  and ``ipctk.tight_inclusion.edge_edge_ccd(ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ea1_t1, eb0_t1,
  eb1_t1, <same keywords>) -> (hit, toi, precision)``: the raw Tight Inclusion solver of Wang et
  al. 2021 (what the sample-query benchmark measures). Points are length-3 float64 arrays. ``toi``
  is a conservative lower bound of the earliest contact (``inf`` when no hit); ``precision`` is the
  tolerance reached (larger than ``tolerance`` when ``max_iterations`` stopped the search early).
* ``ipctk.TightInclusionCCD(tolerance=1e-6, max_iterations=10_000_000, conservative_rescaling=0.8)``
  with methods ``point_triangle_ccd(p_t0, t0_t0, t1_t0, t2_t0, p_t1, t0_t1, t1_t1, t2_t1,
  min_distance=0.0, tmax=1.0) -> (hit, toi)`` and ``edge_edge_ccd(ea0_t0, ..., eb1_t1,
  min_distance=0.0, tmax=1.0) -> (hit, toi)`` (also ``point_edge_ccd``, ``point_point_ccd``): IPC's
  narrow phase, the one ``compute_collision_free_stepsize`` uses. It is NOT a pure contact test
  (ipc-toolkit ``TightInclusionCCD::ccd_strategy``): toi = 0 (and a logged warning) when the
  initial distance d0 <= min_distance; otherwise it runs Tight Inclusion with the minimum
  separation ``min(0.2 * (d0 - min_distance), 1e-4) + min_distance`` (absolute 1e-4: not scale
  invariant, so primitives that only come within that distance count as hits) and the tolerance
  ``min(0.5 * d0, tolerance)``; only when that toi < 1e-6 it reruns at min_distance with
  no_zero_toi and unlimited iterations and multiplies the toi by ``conservative_rescaling``.
  Use the raw solver above for contact truth and times of impact.
* ``ipctk.compute_collision_free_stepsize(mesh: CollisionMesh, vertices_t0, vertices_t1,
  min_distance=0.0, broad_phase=None, narrow_phase_ccd=TightInclusionCCD()) -> float`` in [0, 1];
  ``ipctk.CollisionMesh(rest_positions (V,3) float64, edges (E,2) int32, faces (F,3) int32)``;
  ``ipctk.edges(F)`` builds the unique edges; broad phases ``ipctk.HashGrid()``, ``LBVH()``,
  ``SpatialHash()``, ``SweepAndPrune()``, ``BruteForce()``; ``ipctk.set_num_threads(n)`` (TBB).

Timing: ``time.perf_counter`` around each call (Python call overhead included, one thread; the
narrow-phase functions do not use TBB).
"""

from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np

try:
    import ipctk
except ImportError as e:  # pragma: no cover
    raise SystemExit(f"ipctk is needed for the peer benchmark: pip install 'ipctk==1.6.1' ({e})")

TOLERANCE = 1e-6  # Tight Inclusion / ipctk default (Wang et al. 2021)
MAX_ITERATIONS = int(ipctk.TightInclusionCCD.DEFAULT_MAX_ITERATIONS)  # 10_000_000 in 1.6.1
CONSERVATIVE_RESCALING = float(ipctk.TightInclusionCCD.DEFAULT_CONSERVATIVE_RESCALING)  # 0.8
KINDS = ("vertex-face", "edge-edge")


class PeerResult(NamedTuple):
    hit: np.ndarray  # (N,) bool
    toi: np.ndarray  # (N,) float64, inf where no hit
    seconds: np.ndarray  # (N,) wall time of each call
    precision: np.ndarray  # (N,) precision reached (raw solver), nan for the narrow-phase class

    @property
    def total_s(self) -> float:
        return float(self.seconds.sum())

    @property
    def per_query_s(self) -> float:
        return float(self.seconds.mean()) if len(self.seconds) else float("nan")


def quiet(level: str = "error") -> None:
    """Silence ipctk's per-query warnings (e.g. 'Initial distance 0 ... returning toi=0!')."""
    ipctk.set_logger_level(getattr(ipctk.LoggerLevel, level))


def _check(points) -> np.ndarray:
    pts = np.ascontiguousarray(points, dtype=np.float64)
    if pts.ndim != 3 or pts.shape[1:] != (8, 3):
        raise ValueError(f"queries must be (N, 8, 3), got {pts.shape}")
    return pts


def _raw_fn(kind: str):
    if kind == "vertex-face":
        return ipctk.tight_inclusion.point_triangle_ccd
    if kind == "edge-edge":
        return ipctk.tight_inclusion.edge_edge_ccd
    raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")


def tight_inclusion_queries(
    points,
    kind: str,
    tolerance: float = TOLERANCE,
    max_iterations: int = MAX_ITERATIONS,
    tmax: float = 1.0,
    min_distance: float = 0.0,
    no_zero_toi: bool = False,
) -> PeerResult:
    """The raw Tight Inclusion solver (``ipctk.tight_inclusion.*_ccd``) on each (8, 3) query."""
    pts = _check(points)
    fn = _raw_fn(kind)
    n = len(pts)
    hit = np.zeros(n, dtype=bool)
    toi = np.full(n, np.inf)
    prec = np.full(n, np.nan)
    secs = np.zeros(n)
    rows = [[np.ascontiguousarray(r) for r in q] for q in pts]  # conversion kept out of the timing
    clock = time.perf_counter
    for i, q in enumerate(rows):
        t0 = clock()
        h, t, p = fn(
            *q,
            min_distance=min_distance,
            tmax=tmax,
            tolerance=tolerance,
            max_iterations=max_iterations,
            no_zero_toi=no_zero_toi,
        )
        secs[i] = clock() - t0
        hit[i], toi[i], prec[i] = h, t, p
    return PeerResult(hit, toi, secs, prec)


def narrow_phase_queries(
    points,
    kind: str,
    tolerance: float = TOLERANCE,
    max_iterations: int = MAX_ITERATIONS,
    conservative_rescaling: float = CONSERVATIVE_RESCALING,
    tmax: float = 1.0,
    min_distance: float = 0.0,
) -> PeerResult:
    """IPC's narrow phase ``ipctk.TightInclusionCCD`` (conservative, rescaled toi) on each query."""
    pts = _check(points)
    ccd = ipctk.TightInclusionCCD(tolerance, max_iterations, conservative_rescaling)
    fn = {"vertex-face": ccd.point_triangle_ccd, "edge-edge": ccd.edge_edge_ccd}.get(kind)
    if fn is None:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    n = len(pts)
    hit = np.zeros(n, dtype=bool)
    toi = np.full(n, np.inf)
    secs = np.zeros(n)
    rows = [[np.ascontiguousarray(r) for r in q] for q in pts]
    clock = time.perf_counter
    for i, q in enumerate(rows):
        t0 = clock()
        h, t = fn(*q, min_distance=min_distance, tmax=tmax)
        secs[i] = clock() - t0
        hit[i], toi[i] = h, t
    toi[~hit] = np.inf
    return PeerResult(hit, toi, secs, np.full(n, np.nan))


# drop-in twins of collision.ccd's batched API (argument order as ipctk; each argument (N, 3))


def point_triangle_ccd(p_t0, t0_t0, t1_t0, t2_t0, p_t1, t0_t1, t1_t1, t2_t1, thickness=0.0, **kw):
    """Raw Tight Inclusion per row; returns (hit (N,) bool, toi (N,) float64, inf where no hit).
    ``thickness`` is passed as ipctk's ``min_distance``."""
    pts = np.stack([p_t0, t0_t0, t1_t0, t2_t0, p_t1, t0_t1, t1_t1, t2_t1], axis=1)
    r = tight_inclusion_queries(pts, "vertex-face", min_distance=thickness, **kw)
    return r.hit, r.toi


def edge_edge_ccd(ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ea1_t1, eb0_t1, eb1_t1, thickness=0.0, **kw):
    """Raw Tight Inclusion per row; returns (hit, toi) like ``point_triangle_ccd``."""
    pts = np.stack([ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ea1_t1, eb0_t1, eb1_t1], axis=1)
    r = tight_inclusion_queries(pts, "edge-edge", min_distance=thickness, **kw)
    return r.hit, r.toi


# mesh level


def collision_mesh(V, E=None, F=None) -> "ipctk.CollisionMesh":
    """``ipctk.CollisionMesh`` from (V,3) rest positions, (E,2) edges (None: built from F) and
    (F,3) triangles; arrays are converted to the Fortran-ordered float64 / int32 ipctk wants."""
    V = np.asfortranarray(V, dtype=np.float64)
    F = np.zeros((0, 3), dtype=np.int32) if F is None else np.asfortranarray(F, dtype=np.int32)
    if E is None:
        E = ipctk.edges(F) if len(F) else np.zeros((0, 2), dtype=np.int32)
    E = np.asfortranarray(E, dtype=np.int32)
    return ipctk.CollisionMesh(V, E, F)


def ipctk_stepsize(
    V0,
    V1,
    E=None,
    F=None,
    min_distance: float = 0.0,
    broad_phase=None,
    tolerance: float = TOLERANCE,
    max_iterations: int = MAX_ITERATIONS,
    conservative_rescaling: float = CONSERVATIVE_RESCALING,
    mesh=None,
):
    """Largest collision-free fraction of the linear step V0 -> V1 by
    ``ipctk.compute_collision_free_stepsize`` (broad phase + TightInclusionCCD narrow phase).

    V0 (the rest positions of the collision mesh too, unless ``mesh`` is given) and V1 are (V, 3);
    E (E, 2) (None: from F), F (F, 3). ``broad_phase``: None (ipctk's default) or e.g.
    ``ipctk.HashGrid()``. Returns (stepsize in [0, 1], wall seconds). The narrow phase stops the
    step where the distance first reaches min(0.2 * d0, 1e-4) + min_distance (see the module doc),
    so slightly before contact; V0 must be intersection free.
    """
    if mesh is None:
        mesh = collision_mesh(V0, E, F)
    V0 = np.asfortranarray(V0, dtype=np.float64)
    V1 = np.asfortranarray(V1, dtype=np.float64)
    ccd = ipctk.TightInclusionCCD(tolerance, max_iterations, conservative_rescaling)
    t0 = time.perf_counter()
    step = ipctk.compute_collision_free_stepsize(
        mesh, V0, V1, min_distance=min_distance, broad_phase=broad_phase, narrow_phase_ccd=ccd
    )
    return float(step), time.perf_counter() - t0


def _example_two_triangles():
    """A triangle falling onto another one by 2 units in one step (contact at t = 0.5)."""
    V_lo = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    V_hi = np.array([[0.2, 0.2, 1.0], [1.2, 0.2, 1.0], [0.2, 1.2, 1.0]])
    V0 = np.vstack([V_lo, V_hi])
    V1 = V0.copy()
    V1[3:, 2] -= 2.0
    F = np.array([[0, 1, 2], [3, 4, 5]])
    return V0, V1, F


if __name__ == "__main__":
    quiet()
    V0, V1, F = _example_two_triangles()
    step, secs = ipctk_stepsize(V0, V1, F=F)
    print(f"compute_collision_free_stepsize on two triangles (contact at 0.5): {step:.6f} in {secs * 1e3:.2f} ms")
    pts = np.stack([V0[3], V0[0], V0[1], V0[2], V1[3], V1[0], V1[1], V1[2]])[None]
    r = tight_inclusion_queries(pts, "vertex-face")
    print(f"raw tight_inclusion.point_triangle_ccd on its falling corner: hit={r.hit[0]} toi={r.toi[0]!r}")

"""Loader for the CCD sample queries (Wang et al. 2021 benchmark subset, see the data README).

    from ccd_queries import load_queries
    points, truth, ids = load_queries("vertex-face")      # or "edge-edge"
    points.shape == (N, 8, 3)   # float64, each exact rational rounded to nearest (ties to even)
    truth.shape == (N,)         # bool ground truth of the data set
    ids[i] == ("erleben-spikes", "data_0_1.csv", 17)      # (scene folder, file name, query index in file)

Row order inside a query is ipctk's argument order (README of the data set):
vertex-face ``v_t0, f0_t0, f1_t0, f2_t0, v_t1, f0_t1, f1_t1, f2_t1``; edge-edge
``ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ea1_t1, eb0_t1, eb1_t1``. So
``point_triangle_ccd(*points.transpose(1, 0, 2))`` is the whole batch.

The exact rationals are kept too (Python ints; some numerators/denominators exceed int64):
``load_queries(kind).exact(i)`` is query ``i`` as an (8, 3) nested tuple of ``fractions.Fraction``,
``exact_queries(kind)`` all of them (built lazily and cached). ``representability(kind)`` counts the
coordinates whose rational is not exactly a float64 (then rounding could, in principle, change a
borderline query's truth).

All folders below the data root are read (sorted, so the order is deterministic). The root is
``$TUNNELSIM_CCD_QUERIES`` when set, else ``<repo>/../shared/data/ccd-sample-queries``. Parsed
arrays are cached in memory only (per process).
"""

from __future__ import annotations

import csv
import os
from fractions import Fraction
from functools import lru_cache
from pathlib import Path
from typing import NamedTuple

import numpy as np

KINDS = ("vertex-face", "edge-edge")
ENV_VAR = "TUNNELSIM_CCD_QUERIES"
ROWS_PER_QUERY = 8


def queries_root() -> Path:
    """Folder holding ``<scene>/<kind>/*.csv`` (environment variable first, then the shared data)."""
    env = os.environ.get(ENV_VAR)
    if env:
        return Path(env).expanduser().resolve()
    return Path(__file__).resolve().parents[1].parent / "shared" / "data" / "ccd-sample-queries"


def available() -> bool:
    """True when the data root exists and holds at least one query CSV."""
    root = queries_root()
    return root.is_dir() and any(root.glob("*/*/*.csv"))


def _check_kind(kind: str) -> None:
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")


class _Raw(NamedTuple):
    num: np.ndarray  # (N, 8, 3) object array of Python ints
    den: np.ndarray  # (N, 8, 3) object array of Python ints (> 0)
    truth: np.ndarray  # (N,) bool
    ids: tuple  # ((scene, file, index), ...)


def _parse_file(path: Path):
    with open(path, newline="") as fh:
        rows = [r for r in csv.reader(fh) if r]
    if len(rows) % ROWS_PER_QUERY:
        raise ValueError(f"{path}: {len(rows)} rows, not a multiple of {ROWS_PER_QUERY}")
    vals = [[int(x) for x in r] for r in rows]
    if any(len(r) != 7 for r in vals):
        raise ValueError(f"{path}: every row must have 7 integer columns")
    n = len(vals) // ROWS_PER_QUERY
    num = np.empty((n, ROWS_PER_QUERY, 3), dtype=object)
    den = np.empty((n, ROWS_PER_QUERY, 3), dtype=object)
    truth = np.empty(n, dtype=bool)
    for q in range(n):
        block = vals[q * ROWS_PER_QUERY : (q + 1) * ROWS_PER_QUERY]
        flags = {r[6] for r in block}
        if len(flags) != 1 or not flags <= {0, 1}:
            raise ValueError(f"{path}: query {q} has inconsistent truth flags {flags}")
        truth[q] = bool(flags.pop())
        for j, r in enumerate(block):
            for c in range(3):
                nu, de = r[2 * c], r[2 * c + 1]
                if de == 0:
                    raise ValueError(f"{path}: query {q} row {j}: zero denominator")
                if de < 0:
                    nu, de = -nu, -de
                num[q, j, c] = nu
                den[q, j, c] = de
    return num, den, truth


@lru_cache(maxsize=None)
def _load_raw(kind: str, root: str) -> _Raw:
    files = sorted(Path(root).glob(f"*/{kind}/*.csv"))
    if not files:
        raise FileNotFoundError(
            f"no {kind} query CSVs under {root} (set {ENV_VAR} to the ccd-sample-queries folder)"
        )
    nums, dens, truths, ids = [], [], [], []
    for f in files:
        num, den, truth = _parse_file(f)
        nums.append(num)
        dens.append(den)
        truths.append(truth)
        scene = f.parent.parent.name
        ids.extend((scene, f.name, i) for i in range(len(truth)))
    return _Raw(np.concatenate(nums), np.concatenate(dens), np.concatenate(truths), tuple(ids))


def _to_float(num, den) -> float:
    # int / int in Python is correctly rounded (round to nearest, ties to even).
    return num / den


_to_float_v = np.frompyfunc(_to_float, 2, 1)


class QuerySet(tuple):
    """``points, truth, ids = load_queries(kind)`` (a 3-tuple); also ``.points``, ``.truth``,
    ``.ids``, ``.kind``, ``.root``, and ``.exact(i)`` for query i as Fractions."""

    def __new__(cls, points: np.ndarray, truth: np.ndarray, ids: tuple, kind: str, root: str):
        obj = super().__new__(cls, (points, truth, ids))
        obj.kind = kind
        obj.root = root
        return obj

    points = property(lambda self: self[0], doc="(N, 8, 3) float64, read-only")
    truth = property(lambda self: self[1], doc="(N,) bool, read-only")
    ids = property(lambda self: self[2], doc="((scene, file, index), ...)")

    def exact(self, i: int):
        """Query ``i`` as an (8, 3) nested tuple of ``Fraction`` (the data set's exact values)."""
        raw = _load_raw(self.kind, self.root)
        return tuple(
            tuple(Fraction(raw.num[i, j, c], raw.den[i, j, c]) for c in range(3)) for j in range(ROWS_PER_QUERY)
        )

    def scenes(self) -> np.ndarray:
        """(N,) array of scene folder names (for per-subset tables)."""
        return np.array([s for s, _, _ in self.ids])


@lru_cache(maxsize=None)
def _load(kind: str, root: str) -> QuerySet:
    raw = _load_raw(kind, root)
    pts = _to_float_v(raw.num, raw.den).astype(np.float64)
    pts.setflags(write=False)
    truth = raw.truth.copy()
    truth.setflags(write=False)
    return QuerySet(pts, truth, raw.ids, kind, root)


def load_queries(kind: str, root: str | os.PathLike | None = None) -> QuerySet:
    """All queries of ``kind`` ("vertex-face" or "edge-edge") over every folder of the data root.

    Returns ``(points (N,8,3) float64, truth (N,) bool, ids)`` as a :class:`QuerySet` (a
    3-tuple, so it unpacks; attributes ``points``, ``truth``, ``ids``, ``kind``, ``root``). The arrays are cached and
    read-only: copy before modifying.
    """
    _check_kind(kind)
    root = str(Path(root).resolve()) if root is not None else str(queries_root())
    return _load(kind, root)


@lru_cache(maxsize=None)
def _exact_all(kind: str, root: str) -> tuple:
    qs = _load(kind, root)
    return tuple(qs.exact(i) for i in range(len(qs.truth)))


def exact_queries(kind: str, root: str | os.PathLike | None = None) -> tuple:
    """Every query of ``kind`` as (8, 3) nested tuples of ``Fraction`` (lazy, cached)."""
    _check_kind(kind)
    root = str(Path(root).resolve()) if root is not None else str(queries_root())
    return _exact_all(kind, root)


def _is_exact(num, den) -> bool:
    # den > 0. A rational is a double iff, in lowest terms, den is a power of two and the
    # rounded value converts back exactly (covers the 53-bit significand and the exponent range).
    f = num / den
    return Fraction(f) == Fraction(num, den)


_is_exact_v = np.frompyfunc(_is_exact, 2, 1)


@lru_cache(maxsize=None)
def _not_exact_mask(kind: str, root: str) -> np.ndarray:
    raw = _load_raw(kind, root)
    m = ~_is_exact_v(raw.num, raw.den).astype(bool)
    m.setflags(write=False)
    return m


def representability(kind: str, root: str | os.PathLike | None = None) -> dict:
    """How many coordinates (and queries) of ``kind`` are not exactly representable in float64.

    Returns ``{"coordinates": total, "inexact_coordinates": k, "queries": N,
    "inexact_queries": q, "inexact_mask": (N, 8, 3) bool}``.
    """
    _check_kind(kind)
    root = str(Path(root).resolve()) if root is not None else str(queries_root())
    m = _not_exact_mask(kind, root)
    return {
        "coordinates": int(m.size),
        "inexact_coordinates": int(m.sum()),
        "queries": int(m.shape[0]),
        "inexact_queries": int(m.any(axis=(1, 2)).sum()),
        "inexact_mask": m,
    }


if __name__ == "__main__":  # quick summary
    for k in KINDS:
        qs = load_queries(k)
        rep = representability(k)
        print(
            f"{k}: {len(qs.truth)} queries, {int(qs.truth.sum())} positive; "
            f"{rep['inexact_coordinates']} of {rep['coordinates']} coordinates not exactly float64 "
            f"({rep['inexact_queries']} queries)"
        )
        for scene in sorted(set(qs.scenes())):
            sel = qs.scenes() == scene
            print(f"    {scene:30s} {int(sel.sum()):5d} queries {int(qs.truth[sel].sum()):4d} positive")

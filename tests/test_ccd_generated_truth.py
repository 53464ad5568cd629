"""The CCD ground truth agrees with itself and with the data: generator (tests/ccd_generated.py)
vs exact checker (tests/exact_ccd.py) vs the sample queries' flags (tests/ccd_queries.py).

Deliberately independent of the package's CCD (collision.ccd is never imported here), so a bug
in the narrow phase cannot hide in its own reference.
"""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import os

import pytest

import ccd_generated as gen
import ccd_queries
from exact_ccd import RealAlgebraic, contact_at, coplanarity_cubic, exact_ccd

F = Fraction


@pytest.fixture(scope="module")
def touching():
    return gen.generate_queries(n_per_case=3, seed=0)


@pytest.fixture(scope="module")
def misses():
    return gen.generate_near_misses(n_per_case=2, seed=1)


# ------------------------------------------------------------------------ generated queries


def test_generator_covers_every_case_and_scale(touching):
    assert len(touching.tois) == 3 * 3 * len(gen.CASE_LABELS)
    seen = {(lab.split("/")[0], lab.split("/")[2]) for lab in touching.labels}
    for case in gen.CASE_LABELS:
        for sname, _ in gen.SCALES:
            assert (case, sname) in seen
    assert touching.points.dtype == np.float64 and touching.points.shape[1:] == (8, 3)
    assert np.isfinite(touching.points).all()
    assert all(isinstance(t, Fraction) and 0 <= t <= 1 for t in touching.tois)
    # endpoint cases really sit at the endpoints
    for lab, t in zip(touching.labels, touching.tois):
        if lab.split("/")[0].endswith("-t0") or lab.startswith("ee-collinear-overlap"):
            assert t == 0
        if lab.split("/")[0].endswith("-t1"):
            assert t == 1


def test_generator_is_deterministic_and_scales_are_exact(touching):
    again = gen.generate_queries(n_per_case=3, seed=0)
    assert np.array_equal(again.points, touching.points) and again.labels == touching.labels
    # the three scaled copies of one construction: same contact time, coordinates 2^+-20 apart
    # up to the (different) translation, i.e. differences of rows scale exactly
    by_base = {}
    for i, lab in enumerate(touching.labels):
        case, inst, sname = lab.split("/")
        by_base.setdefault((case, inst), {})[sname] = i
    for (case, _inst), d in by_base.items():
        i1, ib, is_ = d["s=1"], d["s=2^20"], d["s=2^-20"]
        assert touching.tois[i1] == touching.tois[ib] == touching.tois[is_]
        rel = lambda i: touching.points[i] - touching.points[i][0]  # noqa: E731 translation-free
        assert np.array_equal(rel(ib), rel(i1) * 2.0**20), case
        assert np.array_equal(rel(is_), rel(i1) * 2.0**-20), case


def test_every_touching_query_has_the_constructed_exact_toi(touching):
    bad = []
    for i, (kind, t) in enumerate(zip(touching.kinds, touching.tois)):
        r = exact_ccd(touching.exact(i), kind)
        if not (r.hit and isinstance(r.toi, Fraction) and r.toi == t):
            bad.append((touching.labels[i], t, r))
    assert not bad, bad[:5]


def test_touching_queries_bracket_the_contact_directly(touching):
    """Without the root machinery: contact at t*, none shortly before (exact predicate only)."""
    for i, (kind, t) in enumerate(zip(touching.kinds, touching.tois)):
        q = touching.exact(i)
        assert contact_at(q, kind, t), touching.labels[i]
        for k in (3, 17, 45):
            s = t - F(1, 2**k)
            if s >= 0:
                assert not contact_at(q, kind, s), (touching.labels[i], k)
        if t == 0:
            assert contact_at(q, kind, 0)


def test_every_near_miss_misses_exactly(misses):
    bad = []
    for i, kind in enumerate(misses.kinds):
        r = exact_ccd(misses.exact(i), kind)
        if r.hit:
            bad.append((misses.labels[i], r))
    assert not bad, bad[:5]
    assert all(t is None for t in misses.tois)
    labels = {lab.split("/")[0] for lab in misses.labels}
    assert {"vf-outside-edge", "ee-outside-cross", "ee-parallel-late", "vf-sliding-edge-late"} <= labels


def test_coplanar_cases_really_are_coplanar(touching):
    for i, lab in enumerate(touching.labels):
        case = lab.split("/")[0]
        f = coplanarity_cubic(touching.exact(i), touching.kinds[i])
        if case.startswith(("vf-sliding", "ee-sliding", "ee-parallel", "ee-collinear")):
            assert f == (), lab  # identically zero
        elif case in ("vf-interior", "ee-cross"):
            assert f != (), lab


# ------------------------------------------------------------------------------ exact checker


def _q(rows):
    return [[F(x) for x in r] for r in rows]


def test_exact_checker_hand_cases():
    tri0 = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
    # point falling through the triangle interior: toi 1/2 exactly
    q = _q([[F(1, 4), F(1, 4), 1], *tri0, [F(1, 4), F(1, 4), -1], *tri0])
    r = exact_ccd(q, "vertex-face")
    assert r.hit and r.toi == F(1, 2) and not r.coplanar
    # the same path beside the triangle: miss; grazing exactly along the hypotenuse: hit
    q = _q([[F(3, 4), F(3, 4), 1], *tri0, [F(3, 4), F(3, 4), -1], *tri0])
    assert not exact_ccd(q, "vertex-face").hit
    q = _q([[F(1, 2), F(1, 2), 1], *tri0, [F(1, 2), F(1, 2), -1], *tri0])
    assert exact_ccd(q, "vertex-face").toi == F(1, 2)
    # degenerate (collinear) triangle, point crossing its middle segment at t = 1/4
    seg = [[0, 0, 0], [2, 0, 0], [1, 0, 0]]
    q = _q([[1, 0, 1], *seg, [1, 0, -3], *seg])
    r = exact_ccd(q, "vertex-face")
    assert r.hit and r.toi == F(1, 4)
    # everything static and touching: toi 0
    q = _q([[0, 0, 0], *tri0, [0, 0, 0], *tri0])
    assert exact_ccd(q, "vertex-face").toi == 0
    # point-like edges (both degenerate) meeting at t = 3/4
    q = _q([[0, 0, 0], [0, 0, 0], [3, 0, 0], [3, 0, 0], [0, 0, 0], [0, 0, 0], [-1, 0, 0], [-1, 0, 0]])
    r = exact_ccd(q, "edge-edge")
    assert r.hit and r.toi == F(3, 4) and r.coplanar


def test_exact_checker_irrational_toi():
    """Triangle a = 0, b = (1, 0, t), c = (0, 1, 2t) (plane z = t x + 2 t y at time t)."""
    a0 = a1 = [0, 0, 0]
    b0, b1 = [1, 0, 0], [1, 0, 1]
    c0, c1 = [0, 1, 0], [0, 1, 2]
    # static point (1/8, 1/8, 3/8): 3/8 = t/8 + 2t/8  ->  t = 1 (rational, at the endpoint)
    p = [F(1, 8), F(1, 8), F(3, 8)]
    r = exact_ccd(_q([p, a0, b0, c0, p, a1, b1, c1]), "vertex-face")
    assert r.hit and r.toi == 1
    # point (1/8 + 3t/8, 1/8, 1/4): 1/4 = t (1/8 + 3t/8) + t/4  ->  3t^2 + 3t - 2 = 0
    p0, p1 = [F(1, 8), F(1, 8), F(1, 4)], [F(1, 2), F(1, 8), F(1, 4)]
    q = _q([p0, a0, b0, c0, p1, a1, b1, c1])
    r = exact_ccd(q, "vertex-face")
    assert r.hit and isinstance(r.toi, RealAlgebraic)
    assert r.toi.poly == (F(-2, 3), F(1), F(1))  # monic t^2 + t - 2/3
    assert abs(float(r.toi) - (-3 + math.sqrt(33)) / 6) < 1e-15
    assert F(4574, 10000) < r.toi < F(4575, 10000)
    assert contact_at(q, "vertex-face", r.toi)  # exactly, in Q(sqrt(33))
    assert not contact_at(q, "vertex-face", F(4574, 10000))


# --------------------------------------------------------------------------------- data set


needs_data = pytest.mark.skipif(
    not ccd_queries.available() and not os.environ.get("CI"),  # in CI missing data is a failure
    reason="CCD sample queries not found (set TUNNELSIM_CCD_QUERIES)",
)


@needs_data
def test_sample_queries_load():
    vf, ee = ccd_queries.load_queries("vertex-face"), ccd_queries.load_queries("edge-edge")
    for qs, n, pos in ((vf, 3085, 248), (ee, 4194, 187)):
        pts, truth, ids = qs
        assert pts.shape == (n, 8, 3) and pts.dtype == np.float64 and truth.dtype == bool
        assert int(truth.sum()) == pos and len(ids) == n
        assert len({s for s, _, _ in ids}) >= 11
        rep = ccd_queries.representability(qs.kind)
        assert rep["inexact_coordinates"] == 0  # the data set's rationals are all doubles
        i = 5
        ex = qs.exact(i)
        assert np.array_equal(np.array([[float(x) for x in r] for r in ex]), pts[i])
    assert ccd_queries.load_queries("vertex-face") is vf  # cached
    with pytest.raises(ValueError):
        ccd_queries.load_queries("face-face")


def test_loader_env_var_and_inexact_rationals(tmp_path, monkeypatch):
    d = tmp_path / "scene-a" / "vertex-face"
    d.mkdir(parents=True)
    rows = ["1,3,0,1,1,1,1"] + ["0,1,0,1,0,1,1"] * 3 + ["1,3,0,1,-1,1,1"] + ["0,1,0,1,0,1,1"] * 3
    (d / "q.csv").write_text("\n".join(rows) + "\n")
    monkeypatch.setenv(ccd_queries.ENV_VAR, str(tmp_path))
    pts, truth, ids = ccd_queries.load_queries("vertex-face")
    assert pts.shape == (1, 8, 3) and truth.tolist() == [True] and ids == (("scene-a", "q.csv", 0),)
    assert pts[0, 0, 0] == 1 / 3
    rep = ccd_queries.representability("vertex-face")
    assert rep["inexact_coordinates"] == 2 and rep["inexact_queries"] == 1
    assert ccd_queries.load_queries("vertex-face").exact(0)[0][0] == F(1, 3)
    bad = tmp_path / "other-root" / "scene-b" / "vertex-face"
    bad.mkdir(parents=True)
    (bad / "q.csv").write_text("1,1,1,1,1,1,0\n")  # one row: not a whole query
    with pytest.raises(ValueError):
        ccd_queries.load_queries("vertex-face", root=tmp_path / "other-root")
    with pytest.raises(FileNotFoundError):
        ccd_queries.load_queries("edge-edge", root=tmp_path / "other-root")


@needs_data
@pytest.mark.parametrize("kind", ccd_queries.KINDS)
def test_exact_checker_agrees_with_sample_truth(kind):
    """All unit tests, every positive and 150 random negatives of the Erleben scenes (the full
    7279 agree too; about 16 s)."""
    qs = ccd_queries.load_queries(kind)
    scenes = qs.scenes()
    rng = np.random.default_rng(0)
    neg = np.flatnonzero(~qs.truth & (scenes != "unit-tests"))
    idx = np.unique(
        np.concatenate([np.flatnonzero(scenes == "unit-tests"), np.flatnonzero(qs.truth), rng.choice(neg, 150, replace=False)])
    )
    wrong = [qs.ids[i] for i in idx if exact_ccd(qs.exact(int(i)), kind).hit != bool(qs.truth[i])]
    assert not wrong, wrong[:5]

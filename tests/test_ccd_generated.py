"""CCD on queries that touch exactly by construction (``tests/ccd_generated.py``; dyadic
coordinates, exact contact times as Fractions, checked independently by ``tests/exact_ccd.py`` in
``test_ccd_generated_truth.py``): interior / edge / vertex contact, sliding in-plane motion,
contact exactly at t = 0 and t = 1, crossing, parallel and collinear edges, vertex on an edge,
each at scales 1, 2^20 and 2^-20 with dyadic translations and integer affine maps.
"""

import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(__file__))
from ccd_generated import generate_near_misses, generate_queries  # noqa: E402

from collision.ccd import edge_edge_ccd, point_triangle_ccd  # noqa: E402

CCD = {"vertex-face": point_triangle_ccd, "edge-edge": edge_edge_ccd}


@pytest.fixture(scope="module")
def touching():
    return generate_queries(n_per_case=4, seed=11)


@pytest.mark.parametrize("kind", ["vertex-face", "edge-edge"])
def test_no_exact_touch_is_missed_and_times_match(touching, kind):
    pts, tois, labels = touching.select(kind)
    assert len(tois) > 50
    hit, toi = CCD[kind](*[pts[:, k] for k in range(8)])
    missed = [labels[i] for i in np.nonzero(~hit)[0]]
    assert not missed, f"missed exact contacts: {missed[:10]}"
    exact = np.array([float(t) for t in tois])
    # transversal contacts: the time of the computed root; coplanar (sliding) steps: the time
    # of a vertex-edge collinearity root. Both are exact to rounding here.
    err = np.abs(toi - exact)
    worst = int(np.argmax(err))
    assert err.max() <= 1e-12, f"{labels[worst]}: toi {toi[worst]!r} vs exact {tois[worst]}"


@pytest.mark.parametrize("kind", ["vertex-face", "edge-edge"])
def test_near_misses_mostly_reported_as_misses(kind):
    """Misses by 2^-30 of the scale: inside the tolerance a hit may be reported (conservative,
    like Tight Inclusion's 1e-6 box), but most must come out as misses, and none far off."""
    near = generate_near_misses(n_per_case=3, seed=5)
    pts, _, labels = near.select(kind)
    hit, _ = CCD[kind](*[pts[:, k] for k in range(8)])
    assert hit.mean() <= 0.25, f"{hit.sum()} of {len(hit)} near misses reported as hits"

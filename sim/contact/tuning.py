"""The collision response's tuning constants: separation, proximity, the Gauss-Seidel solve, the
broad-phase cover, the active set and the contact limits. Each docstring says what the constant
trades and, where a value was chosen by measurement, what was measured.
"""

SEPARATION_RATE = 0.1
"""Fraction of the missing separation ``delta - d`` a proximity impulse restores per substep
(Bridson et al. 2002 use the same order); larger values make resting contacts jitter."""

PROXIMITY_HYSTERESIS = 1e-3
"""The proximity pass keeps mesh pairs and rigid vertex-plane pairs up to ``(1 +
PROXIMITY_HYSTERESIS) delta`` apart, not just nearer than ``delta``: resting contact ends each
substep at ``delta`` to rounding, and a load-bearing pair that rounding put a hair beyond it
would otherwise leave the set for a substep, drop its load and kick the cloth (a draped cloth
crept 2.6e-5 m/s). A pair beyond ``delta`` may approach until it reaches ``delta`` at the end of
the substep (:func:`kernels.contact_geometry.contact_geometry_kernel`), so the band holds no pair that
approaches slower than the separation speed before it touches ``delta``; one approaching faster
bounces (restitution) up to ``1e-3 delta`` early."""

DEFAULT_SEPARATION_RELATIVE = 1e-4
"""Separation used when the model's thickness is 0: this fraction of the diagonal of the
collidable vertices' bounding box at the start (1e-4 m for a 1 m scene)."""

SOLVER_ITERATIONS = 500
"""Most projected Gauss-Seidel sweeps per impulse solve (it stops earlier once every contact's normal
velocity is within :data:`SOLVER_TOLERANCE` of its target)."""

SOLVER_TOLERANCE = 0.05
"""Stop the Gauss-Seidel sweeps when no contact's normal velocity is below its target by more than this
fraction of the separation speed ``SEPARATION_RATE delta / h``."""

TOUCHING_RELATIVE = 1e-6
"""Proximity pairs closer than this fraction of the separation count as touching: their offset
direction is rounding noise, so the normal comes from the primitives' geometry instead (a
face's outward normal, crossing edges' cross product), or, where the geometry gives none (a
vertex on a face's border, edges touching at an end), the pair joins no contact set."""

APPROACH_EPS = 1e-12
"""A CCD hit counts as approaching when its normal relative velocity is below ``-APPROACH_EPS``
times the contact's largest vertex speed plus the separation speed (float64 rounding of a
velocity that is exactly separating or tangential stays far inside)."""

END_OF_SUBSTEP = 1e-9
"""A CCD hit this close (relative) to the end of the substep lies on the end of the planned path;
its approach is judged by the velocities at ``t*`` alone (see :meth:`sim.contact.detect.ContactDetection.approach`)."""

PLANE_ROUNDING_SLACK = 1e-9
"""A particle counts as a plane's proximity contact below ``(1 - PLANE_ROUNDING_SLACK) delta``:
the integrator's plane stage leaves it at ``delta`` exactly, which the distance's rounding may
put a hair below (rigid vertices, which only the handler holds, count up to ``(1 +
PROXIMITY_HYSTERESIS) delta``)."""

COVER_MARGIN = 4.0
"""Margin of the substep's one broad-phase query, in separations ``delta``: the proximity pass
and every CCD round whose planned end positions stay within ``0.45 COVER_MARGIN delta`` of the
covered boxes (the predicted motion continued, :data:`COVER_AHEAD`) reuse its candidates
(:class:`collision.narrow_phase.CandidateNarrowPhase`); a round that moves further queries afresh."""

COVER_SLACK = 1.0
"""A substep keeps an earlier substep's broad-phase query (instead of a new one) while its start
and predicted end positions lie within this many separations ``delta`` of the boxes of the
covered motion (per coordinate): slow and resting contact moves less than that per substep, so
one query serves several substeps. The
proximity pass still has ``0.45 (COVER_MARGIN - 1) delta - COVER_SLACK delta >= 0`` of room and
the CCD rounds ``0.45 COVER_MARGIN delta - COVER_SLACK delta``; a call beyond its room queries
afresh, so the contacts are the same as with a query per substep."""

CCD_REACH_SLACK = 0.5
"""How much farther than predicted [separations] a vertex may end from its start before the
CCD rounds test every candidate instead of those that the proximity pass kept for them
(:meth:`sim.contact.detect.ContactDetection.proximity_hits`). Resting contact's rounds change the
predicted motion by about ``SEPARATION_RATE`` separations; measured over 100 steps, 0.5 kept
the short list in 96% of cloth_drop's CCD rounds (154 pairs instead of ~2000), 0.25 in 89%
(55 pairs), 1.0 in 98% (343 pairs)."""

CCD_REACH_MIN_CANDIDATES = 64
"""Fewest candidate pairs of the cover for which the proximity pass keeps the CCD rounds'
pairs: below it, testing them all costs about what keeping them does (rigid_toss has ~30-50).
A wide cover (:data:`COVER_SCALES`) holds a few hundred: cloth_rigid's CCD rounds then test 63
pairs per substep instead of 233."""

COVER_AHEAD = 5.0
"""The substep's broad-phase query covers each vertex's predicted motion continued for this
many more substeps (at most :data:`COVER_AHEAD_LIMIT` separations per coordinate), so that
steady motion stays inside its covered box, and the cover is kept (:data:`COVER_SLACK`), for
several substeps. The hits are the same (the calls check their own motion against the covered
one); the pairs the query finds grow only along the motion. Measured on the benchmark scenes
(300 steps): broad-phase queries 2479 -> 872 (cloth_rigid, whose cloth swings about 4
separations per substep), 1117 -> 386 (cloth_drop), 346 -> 83 (rigid_toss)."""

COVER_AHEAD_LIMIT = 32.0
"""Longest continuation [separations] of a vertex's motion in the broad-phase query (fast
vertices leave their cover anyway; this keeps their boxes, and the candidate pairs, small)."""

COVER_SCALES = (1.0, 2.0, 4.0, 8.0)
"""Factors on :data:`COVER_MARGIN`, :data:`COVER_SLACK` and :data:`COVER_AHEAD_LIMIT`: a scene
whose broad-phase queries find few candidate pairs (a cloth swinging free, a ball rolling on a
floor) widens its cover a step after each query that finds fewer than
:data:`COVER_SPARSE_CANDIDATES`, and narrows it a step after each that finds more than
:data:`COVER_DENSE_CANDIDATES` (a draped cloth). A wide cover is kept for more substeps of
fast or turning motion, at the price of more candidates to test per call; the hits are the same
whatever the cover. Measured on cloth_rigid (hanging cloth and rolling ball), steps 20-100:
0.46 queries per substep at factor 1 (29 candidates each), 0.18 at factor 8 (186)."""

COVER_SPARSE_CANDIDATES = 128
"""See :data:`COVER_SCALES`."""

COVER_DENSE_CANDIDATES = 1024
"""See :data:`COVER_SCALES`."""

DEVICE_SORT_MIN = 2048
"""Off the CPU, a detection pass whose bound on its hits (the candidates tested plus the
vertex-plane rows: the count itself stays on the device) is above this is put in order by Warp's
radix sort (a thread per key) instead of the one-thread heap sort
(:func:`kernels.contact_set.sort_hit_keys_kernel`);
both give the same order (distinct keys). On the CPU the heap sort is used always: its threads
run one after another anyway, and the radix sort costs ~75 us at any size there."""

ACTIVE_SET_ITERATIONS = 20
"""Most repairs of the active set (drop pulling contacts, add violated ones, switch between
sticking and sliding) after the exact solve of the replayed response."""

ACTIVE_SET_COLLIDED_MAX_CONTACTS = 128
"""Largest contact set in which the rows that a CCD hit reached are repaired to the approach
test's tolerance (``APPROACH_EPS`` times the separation speed) instead of the active set's:
their primitives meet within the substep, so any approach left over is a hit of the next CCD
round again, and a cloth landing on a sphere and a box ran its eight rounds into the fail-safe
on one contact violated by less than the active set's tolerance. Larger sets (a ball at
200 m/s into a cloth: a few hundred rows) keep the active set's tolerance: there the tight one
made the repairs thrash for minutes per step, and the fail-safe takes what is left."""

ACTIVE_SET_PULLING = 1e-9
"""An active contact leaves the replayed response's active set when its exact normal impulse is
below ``-ACTIVE_SET_PULLING`` times the largest one (it pulls; rounding of a zero impulse stays
above)."""


MAX_HITS_PER_VERTEX = 8
"""A collision round whose narrow phase finds more hits than this many per collision vertex (at least
:data:`MAX_HITS_MIN`) stops with :class:`ContactLimitExceeded`: a resting cloth has about one
per vertex, and tens of thousands of hits mean a substep far too long for the motion (every
triangle sweeping across the scene), whose exact solve would take minutes."""
MAX_HITS_MIN = 4096


REGULARIZATION = 1e-8
"""Relative diagonal regularisation of the active set's matrix: redundant contacts (two
constraints on the same relative velocity) make it singular; scaling the diagonal by
``1 + 1e-8`` picks a bounded solution while moving velocities by ~1e-8 relative. (Measured on a
box resting face-down with friction: 1e-10 leaves the matrix so ill-conditioned that finite
differences of the result scatter by 100 %; 1e-8 and 1e-6 give gradients within 2e-5 and 4e-4
of central differences at step 1e-5 and 1e-6.)"""


MAX_SOLVE_WORK = 1.0e11
"""The most work the exact impulse solves of one substep may take: the sum of ``n^3`` over its
dense solves of ``n`` unknowns (1e11 is about 20 s on one CPU thread). Measured largest
substeps: 3e8 in the three simulation scenes over 300 steps, 4.2e10 for a ball at 200 m/s into
a hanging cloth, 2.4e10 for a cloth hitting a box in one implicit substep per step. A substep
far too long for the motion (``cloth_drop`` at ``--dt 1`` with the implicit integrator: 1.2e11
in its first heavy substep) stops with :class:`sim.contact.contacts.ContactLimitExceeded`."""


PUSH_OVERSHOOT = 100.0
"""The push's solve (:meth:`ContactReplay._pushed`) is redone with
:data:`PUSH_REGULARIZATION` when an impulse alone changes its own row's velocity by more than
this many times the largest push asked for. The push's rows are every contact short of its
separation, and near-copies of one constraint with different missing separations (a cloth
particle near a face's edge and the neighbour face) ask for pushes no bounded impulse gives:
with :data:`REGULARIZATION` their impulses cancel at a large scale, and a rounding error of that
scale moved a cloth particle 0.15 m in a 2 ms substep (tens of m/s of push)."""


PUSH_REGULARIZATION = 1e-2
"""The push's relative diagonal regularisation where :data:`PUSH_OVERSHOOT` says so: a
consistent push is met to 1 % (the next substep's push makes up the rest), an inconsistent one
stays bounded."""


STICKING_MAX_CONTACTS = 48
"""Most active contacts for which a solve tries static friction as one system (three unknowns
each, a dense solve of ``(3 n)^3``): a few resting boxes, a small draped cloth. Larger sets
take the friction pass (each contact's stopping impulse, shared)."""


SLIP_REVERSAL = 1e-9
"""A sliding contact whose slip after the solve runs against its friction direction by more than
this [m/s] sticks instead (rounding of a slip that stopped exactly stays far below)."""


FRICTION_SPLIT_ITERATIONS = 8
"""Most solves of the frictional system while its split into sticking and sliding contacts
changes (:meth:`FrictionSplit.mixed`); a split that still changes, or returns to one it
tried, gives way to the friction pass."""

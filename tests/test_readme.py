"""The README's runnable examples, executed from the README itself (so the text cannot rot).

Blocks are found by their first line; the API sketches (roots, CCD) have placeholders and are
not run. Ground truth is closed-form physics: one step of free fall of semi-implicit Euler.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parents[1] / "README.md"
G = 9.81


def readme_block(first_line: str) -> str:
    """The README's ```python block that starts with ``first_line``."""
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.DOTALL)
    found = [b for b in blocks if b.startswith(first_line)]
    assert len(found) == 1, f"expected one README python block starting {first_line!r}, found {len(found)}"
    return found[0]


def run_block(first_line: str) -> dict:
    namespace: dict = {}
    exec(compile(readme_block(first_line), f"README ({first_line})", "exec"), namespace)
    return namespace


def test_simulator_quick_start_is_one_step_of_free_fall():
    """"Simulator" block: a cloth 1 m up, a ball 2 m up, a box and the ground; one step of 1/60 s
    in 8 substeps touches nothing, so every particle and the ball fall by semi-implicit Euler's
    g h^2 (1 + ... + 8) = 36 g h^2 (h = 1/480 s) from rest."""
    ns = run_block("from sim.builder import ModelBuilder\nfrom sim.integrators.semi_implicit import SemiImplicitIntegrator")
    s0, s1 = ns["s0"], ns["s1"]
    drop = 36.0 * G * (1.0 / 480.0) ** 2
    q0, q1 = s0.particle_q.numpy(), s1.particle_q.numpy()
    assert q0.shape == (17 * 17, 3)
    np.testing.assert_allclose(q0[:, 2] - q1[:, 2], drop, rtol=1e-9)
    np.testing.assert_array_equal(q1[:, :2], q0[:, :2])
    b0, b1 = s0.body_q.numpy(), s1.body_q.numpy()
    np.testing.assert_allclose(b0[:, 2] - b1[:, 2], drop, rtol=1e-9)
    assert np.isfinite(s1.particle_qd.numpy()).all() and np.isfinite(s1.body_qd.numpy()).all()


def test_rollout_example_optimises_a_bounce_to_a_target(monkeypatch):
    """"Differentiable rollout" block: Adam on a particle's initial velocity so that, after
    bouncing off a tilted box, it ends at a target: every iterate bounces (as the comment says),
    the first loss is > 0.2 m^2 and the last < 1e-4 m^2 (the comment says 0.26 -> 4e-5). The
    block runs as written, with one line appended to its loop that records the loss."""
    import sim.rollout

    contacts = []
    real_rollout = sim.rollout.rollout

    def recording_rollout(*args, **kwargs):
        result = real_rollout(*args, **kwargs)
        contacts.append(result.stats["contact_substeps"])
        return result

    monkeypatch.setattr(sim.rollout, "rollout", recording_rollout)  # the block imports it from there
    block = readme_block("import torch\nfrom sim.builder import ModelBuilder")
    iterations = int(re.search(r"for it in range\((\d+)\)", block).group(1))
    assert block.rstrip().endswith("opt.step()"), "the loop must end the block (a line is appended to it)"
    ns: dict = {"losses": []}
    exec(compile(block.rstrip() + "\n    losses.append(float(loss.detach()))\n", "README (rollout)", "exec"), ns)
    losses = ns["losses"]
    assert len(losses) == len(contacts) == iterations and min(contacts) >= 1
    assert losses[0] > 0.2 and losses[-1] < 1e-4

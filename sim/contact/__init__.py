"""The collision stage: the handler (:mod:`sim.contact.response`), its detection
(:mod:`sim.contact.detect`), the two responses (:mod:`sim.contact.replayed`,
:mod:`sim.contact.gauss_seidel`), the taped replay (:mod:`sim.contact.replay`) and what they share.
See docs/architecture.md, "One substep"."""

"""A griffe extension for the API reference (mkdocs.yml): the docstrings cross-reference in
Sphinx's style (:class:`sim.model.Model`, :func:`rollout`), which Markdown does not know; this
shows each such reference as inline code, the way the rest of the docstrings write names."""

from __future__ import annotations

import re

import griffe

_ROLE = re.compile(r":(?:class|func|meth|attr|data|mod|exc|obj|py:\w+):`~?([^`]+)`")


class SphinxRoles(griffe.Extension):
    def on_object(self, *, obj, **kwargs) -> None:
        if obj.docstring is not None:
            obj.docstring.value = _ROLE.sub(r"`\1`", obj.docstring.value)

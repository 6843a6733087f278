"""A griffe extension for the API page: fmusa's docstrings use reST roles (``:func:`x```) and literals
(````x````); mkdocstrings renders docstrings as Markdown, so the roles become inline code."""
from __future__ import annotations

import re

import griffe

_ROLE = re.compile(r":(?:func|meth|class|mod|attr|data|exc|obj):`~?([^`]+)`")


class ReSTRoles(griffe.Extension):
    def on_instance(self, *, obj: griffe.Object, **kwargs: object) -> None:
        if obj.docstring is not None:
            obj.docstring.value = _ROLE.sub(r"`\1`", obj.docstring.value)

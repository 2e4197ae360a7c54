"""A griffe extension of the API pages: the Sphinx cross-reference roles of the
docstrings (``:class:`Model```, ``:func:`~jaxcal.calibrate```) read as code spans.

mkdocstrings renders docstrings as Markdown, where a role would show as the text
``:class:`` before the name. ``~`` keeps the last dotted part, as in Sphinx. Loaded by
``mkdocs.yml`` (``plugins.mkdocstrings...extensions``); not part of the site.
"""

import re

from griffe import Extension

ROLE = re.compile(r":(?:class|func|meth|mod|attr|data|exc|obj|const):`(~?)([^`]+)`")


def _code(match: re.Match) -> str:
    tilde, target = match.groups()
    return f"`{target.rsplit('.', 1)[-1] if tilde else target}`"


def plain_roles(text: str) -> str:
    """``text`` with every Sphinx role replaced by a code span of its target."""
    return ROLE.sub(_code, text)


class SphinxRoles(Extension):
    """Rewrites each object's docstring once, when griffe creates the object."""

    def on_instance(self, *, obj, **kwargs) -> None:
        if obj.docstring is not None:
            obj.docstring.value = plain_roles(obj.docstring.value)

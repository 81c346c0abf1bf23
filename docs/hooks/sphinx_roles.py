"""Sphinx roles in docstrings as the site's cross-references (a Griffe extension, mkdocs.yml).

fedhpg's docstrings name objects with Sphinx roles (``:func:`run```, ``:class:`~a.b.C```),
which the API reference's Markdown would show as raw text. Once the package is loaded, each
role becomes mkdocs-autorefs' optional reference to the object, its name resolved in the
docstring's scope: a link where the site documents the object, the name in code where not.
``~a.b.c`` shows ``c``, ``title <a.b.c>`` shows ``title``, ``!name`` is never a link.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from html import escape
from typing import Any

import griffe

ROLE = re.compile(r":(?:py:)?(?:func|class|mod|meth|attr|data|exc|obj|const):`(?P<text>[^`]+)`")


def _objects(obj: griffe.Object) -> Iterator[griffe.Object]:
    yield obj
    for member in obj.members.values():
        if isinstance(member, griffe.Object):  # not an import (griffe.Alias)
            yield from _objects(member)


def _resolve(scope: griffe.Object, name: str) -> str:
    """The full path of ``name`` as written in ``scope``'s docstring (as is if unknown)."""
    name = name.lstrip(".")
    try:
        scope.modules_collection[name]  # a full path already
        return name
    except (KeyError, griffe.AliasResolutionError, griffe.CyclicAliasError):
        pass
    head, _, rest = name.partition(".")
    try:
        path = scope.resolve(head)
    except griffe.NameResolutionError:
        return name
    return f"{path}.{rest}" if rest else path


def _reference(scope: griffe.Object, text: str) -> str:
    explicit = re.fullmatch(r"(?P<title>.+?)\s*<(?P<target>[^<>]+)>", text, re.DOTALL)
    if explicit:
        title, target = explicit["title"], explicit["target"]
    else:
        target = text.lstrip("!~")
        title = target.rsplit(".", 1)[-1] if text.lstrip("!").startswith("~") else target
    code = f"<code>{escape(title.lstrip('.'))}</code>"
    if text.startswith("!"):
        return code
    identifier = escape(_resolve(scope, target.lstrip("!~")))
    return f'<autoref identifier="{identifier}" optional>{code}</autoref>'


def _rewrite(scope: griffe.Object, docstring: str) -> str:
    return ROLE.sub(lambda match: _reference(scope, match["text"]), docstring)


class SphinxRoles(griffe.Extension):
    """Rewrite every docstring's Sphinx roles once the package is loaded."""

    def on_package(self, *, pkg: griffe.Module, **kwargs: Any) -> None:
        for obj in _objects(pkg):
            if obj.docstring is not None:
                obj.docstring.value = _rewrite(obj, obj.docstring.value)

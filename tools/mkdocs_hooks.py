"""mkdocs hooks (``hooks:`` in mkdocs.yml): the API pages render magrun's numpydoc docstrings
clean.

- Sphinx cross-reference roles, which mkdocstrings shows as written (":class:`~a.b.C`"),
  become code spans: ``~a.b.C`` shows ``C``, ``a.b.C`` shows ``a.b.C``, as Sphinx would.
- A class whose bases are all private (pydantic's ``_Strict`` helper) shows no "Bases:" line.

tests/test_docs.py checks the built HTML for both.
"""

from __future__ import annotations

import re
from typing import Any

#: a role as mkdocstrings renders it: the role name, then the target in a code span
ROLE = re.compile(
    r":(?:py:)?(?:class|meth|func|mod|attr|data|exc|obj|const|ref|term):<code>(~?)([^<]+)</code>"
)
#: a "Bases:" paragraph that names private classes only
PRIVATE_BASES = re.compile(
    r'<p class="doc doc-class-bases">\s*Bases:\s*'
    r'(?:<code><span title="[^"]*">_\w*</span></code>(?:,\s*)?)+</p>'
)


def _shown(match: re.Match[str]) -> str:
    target = match.group(2)
    return f"<code>{target.rsplit('.', 1)[-1] if match.group(1) else target}</code>"


def clean(html: str) -> str:
    """``html`` with the roles as code spans and private-only bases dropped."""
    return PRIVATE_BASES.sub("", ROLE.sub(_shown, html))


def on_page_content(html: str, **_: Any) -> str:
    return ROLE.sub(_shown, html)  # before the search index is built from it


def on_post_page(output: str, **_: Any) -> str:
    return clean(output)  # the bases' cross-references are resolved by now

"""The documentation site's API pages: magrun's numpydoc docstrings rendered without raw
Sphinx roles or private bases (tools/mkdocs_hooks.py, which mkdocs.yml runs)."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("mkdocs_hooks", REPO / "tools" / "mkdocs_hooks.py")
assert _spec is not None
assert _spec.loader is not None
hooks = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(hooks)


def test_roles_become_code_spans_as_sphinx_shows_them() -> None:
    html = (
        "<p>raises :class:<code>~magrun.yamlio.YamlModelError</code>; see "
        ":meth:<code>expand</code> and :func:<code>magrun.loop.run_trial</code>, "
        ":py:data:<code>~magrun.x.LIMIT</code></p>"
    )
    assert hooks.clean(html) == (
        "<p>raises <code>YamlModelError</code>; see <code>expand</code> and "
        "<code>magrun.loop.run_trial</code>, <code>LIMIT</code></p>"
    )


def test_private_bases_are_dropped_and_public_ones_kept() -> None:
    private = (
        '<p class="doc doc-class-bases">\n  Bases: <code><span title="magrun.protocol._Strict">'
        "_Strict</span></code></p>"
    )
    public = (
        '<p class="doc doc-class-bases">\n  Bases: <code><span title="abc.ABC">ABC</span>'
        "</code></p>"
    )
    assert hooks.clean(f"<div>{private}</div>") == "<div></div>"
    assert hooks.clean(public) == public


def test_every_role_in_the_api_docstrings_is_one_the_hook_renders() -> None:
    """The roles magrun's and analysis's sources use are all of the kinds the hook turns
    into code spans (a new kind would show raw on the site: add it to the hook)."""
    used = set()
    for path in [*REPO.joinpath("magrun").rglob("*.py"), *REPO.joinpath("analysis").rglob("*.py")]:
        used |= set(re.findall(r"(?<![\w`]):((?:py:)?[a-z]+):`", path.read_text(encoding="utf-8")))
    assert used >= {"class", "func", "meth"}  # the scan sees them
    for role in used:
        rendered = f":{role}:<code>~a.b.C</code>"
        assert hooks.clean(rendered) == "<code>C</code>", role

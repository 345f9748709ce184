"""MkDocs hook: the docstrings use Sphinx roles (``:class:`~jaxlag.System```); Markdown renders
them as a role name followed by code. Drop the role and, as Sphinx does for ``~``, keep only the
last component of the name."""

import re

_ROLE = re.compile(r":(?:class|func|meth|mod|attr|data|exc|obj):<code>(~?)([\w.]+)(\(\))?</code>")


def _short(match: re.Match) -> str:
    tilde, name, call = match.groups()
    return f"<code>{name.rsplit('.', 1)[-1] if tilde else name}{call or ''}</code>"


def on_page_content(html, **kwargs):
    return _ROLE.sub(_short, html)

"""MkDocs hook: Sphinx roles in docstrings (``:class:`X```, ``:func:`f```, ...) shown as code.

The docstrings cross-reference with Sphinx roles; Markdown renders the role's name as text in
front of the code span (":class:Subscriber"). This drops the role's name and keeps the code.
"""

from __future__ import annotations

import re
from typing import Any

_ROLE = re.compile(r":(?:py:)?(?:class|func|meth|mod|data|attr|exc|obj|const):(?=<code>)")


def on_page_content(html: str, **_: Any) -> str:
    return _ROLE.sub("", html)

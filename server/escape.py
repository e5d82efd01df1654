"""Text from the network into the dashboard's HTML: the one escaping helper.

Whatever a controller, a peer on the same router, a recording or a browser sent (rig names,
lease holders, faults, notes, verdicts, knowledge sources, history clients, file names,
messages) reaches the page through `esc`: element text and attribute values, which the
dashboard always writes quoted (`&`, `<`, `>`, `'` and `"` all escaped, so the same text is
safe in both). A link's target goes through `href` (http(s) or a path of this dashboard, never
`javascript:` or another scheme). The dashboard builds no markdown from such text: markdown
renders HTML, so the panels use `add_html` with `esc` instead.
tests/test_escape.py checks the contexts; tests/browser/test_hostile_names_browser.py checks
every view in Chromium with hostile names.
"""

from __future__ import annotations

import html

__all__ = ["esc", "href"]

_SAFE_URL_PREFIXES = ("http://", "https://", "/")


def esc(text: str) -> str:
    """`text` for HTML element content or a quoted attribute value (never unquoted)."""
    return html.escape(str(text), quote=True)


def href(url: str) -> str:
    """`url` for a quoted `href`/`src` attribute: http(s) or a path of this site (not `//`);
    ValueError naming it for any other scheme (`javascript:`, `data:`, ...)."""
    if (
        not isinstance(url, str)
        or not url.lower().startswith(_SAFE_URL_PREFIXES)
        or url.startswith("//")
        or any(c.isspace() or not c.isprintable() for c in url)
    ):
        raise ValueError(f"url {url!r}: only http(s) or a path of this dashboard is linked")
    return esc(url)

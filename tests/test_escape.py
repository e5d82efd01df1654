"""server.escape: the one way network text enters the dashboard's HTML (issue 24, item 1)."""

from __future__ import annotations

import html.parser
import re
from pathlib import Path

import pytest

from server.escape import esc, href

ROOT = Path(__file__).resolve().parents[1]
HOSTILE = ("x' onmouseover='alert(9)' data-y='", '"><script>alert(1)</script>',
           "<img src=x onerror=alert(2)>", "a & b &amp; c", "javascript:alert(3)")


class _Collect(html.parser.HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.tags: list[tuple[str, list[tuple[str, str | None]]]] = []
        self.text: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.tags.append((tag, attrs))

    def handle_data(self, data: str) -> None:
        self.text.append(data)


@pytest.mark.parametrize("payload", HOSTILE)
@pytest.mark.parametrize("quote", ["'", '"'])
def test_text_and_attribute_contexts_keep_the_payload_as_data(payload: str, quote: str) -> None:
    page = f"<tr class='row' data-rig={quote}{esc(payload)}{quote}><td>{esc(payload)}</td></tr>"
    p = _Collect()
    p.feed(page)
    p.close()
    assert [t for t, _ in p.tags] == ["tr", "td"]  # no element of the payload's
    assert p.tags[0][1] == [("class", "row"), ("data-rig", payload)]  # no attribute either
    assert "".join(p.text) == payload


@pytest.mark.parametrize("url", ["javascript:alert(1)", "JavaScript:alert(1)", " javascript:x",
                                 "data:text/html,<script>", "//evil.example/x", "vbscript:x",
                                 "/ok\njavascript:x", ""])
def test_a_link_target_is_http_or_a_path_of_the_dashboard(url: str) -> None:
    with pytest.raises(ValueError, match="url"):
        href(url)


def test_safe_link_targets_are_escaped_for_a_quoted_attribute() -> None:
    assert href("http://127.0.0.1:8081/?t=a&b='c'") == "http://127.0.0.1:8081/?t=a&amp;b=&#x27;c&#x27;"
    assert href("/rig/x") == "/rig/x"


def test_the_server_escapes_only_through_server_escape() -> None:
    """No second escaping helper, no markdown built from values (markdown renders HTML)."""
    bad = []
    for path in sorted((ROOT / "server").rglob("*.py")):
        if path.name == "escape.py" and path.parent.name == "server":
            continue
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if re.search(r"html\.escape|quote=False|add_markdown\(\s*f[\"']", line):
                bad.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()}")
    assert not bad, bad

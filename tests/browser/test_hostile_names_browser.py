"""Hostile text from the network in every view of the dashboard, in headless Chromium (issue 24).

A router with one simulated rig (rig1, a real controller process) and a dashboard with the
fleet overview behind it. A hostile peer on the router (no `--auth`: anyone who reaches a
loopback router may) declares rigs whose names are script payloads and puts their Status with
payloads in every text field; through the real controller, a client named with a payload
applies a configuration (History) and sends plant knowledge from a payload source (the banner,
the verdict); the recordings directory holds files named with payloads. Every payload
tries to run script (`window.__pwned`, `alert`); the test hovers every fleet row and visits
every tab, then checks that no script ran, no dialog opened, and the payloads are shown as
text, letter for letter (the fleet's `data-rig` attributes included).
"""

from __future__ import annotations

import contextlib
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgspec
import pytest
import zenoh
from conftest import CONTROLLER_START_S, FIRST_LOAD_S, VIEWPORT, free_port
from helpers import wait_for
from test_fleet_browser import _free_run

from controller import protocol as proto
from controller.client import ClientOptions, ControllerClient
from controller.client.session import zenoh_config
from controller.core.config import LoopConfig
from controller.gate.knowledge import KnowledgeRecord
from server.dashboard.app import Dashboard, DashboardOptions
from server.dashboard.demo import DemoOptions, fleet_processes

pytestmark = pytest.mark.browser

#: Rig names (key chunks: no '/', '*', '$', '?', '#'), each trying another HTML context.
HOSTILE_RIGS = (
    "x' onmouseover='window.__pwned=1' data-y='",  # out of a single-quoted attribute
    '"><img src=x onerror="window.__pwned=2">',  # out of a double-quoted one
    "<svg onload=alert(3)>",
    "javascript:alert(4)",
)
#: Text fields (any character).
HOSTILE_TEXT = "<script>window.__pwned=5</script><img src=x onerror=alert(6)> ' \" &amp;"
HOSTILE_FILE = "<img src=x onerror=alert(7)>'x.mcap"

PWNED_JS = "() => [window.__pwned === undefined ? null : String(window.__pwned)]"


@pytest.fixture(scope="module")
def hostile() -> Iterator[dict[str, Any]]:
    base = _free_run(1)
    router = f"tcp/127.0.0.1:{base}"
    with tempfile.TemporaryDirectory() as root, fleet_processes(
            DemoOptions(zenoh_port=base, rigs=1, log_level="warning"), Path(root)):
        recordings = Path(root) / "recordings"
        recordings.mkdir()
        (recordings / HOSTILE_FILE).write_bytes(b"not an mcap file")
        # Through the real controller: a client named with a payload applies and sends
        # knowledge (no authentication: the controller serves it as `local`).
        opts = ClientOptions(connect=(router,), rig_name="rig1", client_name=HOSTILE_TEXT,
                             query_timeout_s=10.0)
        with ControllerClient(opts) as c:
            wait_for(lambda: c.status is not None, CONTROLLER_START_S, "rig1 did not come up")
            assert c.apply(LoopConfig(q_cutoff_hz=0.65)).accepted
            k = c.knowledge(proto.KnowledgeRequest(record=KnowledgeRecord(source=HOSTILE_TEXT)))
            assert k.ok, k
            real = c.status
        assert real is not None and real.verdict is not None
        # The running verdict, nested (protocol 2), with payloads in its text fields.
        judged = msgspec.structs.replace(real.verdict, knowledge=HOSTILE_TEXT,
                                         cautions=(HOSTILE_TEXT,))
        conf = zenoh_config((), [router])
        conf.insert_json5("mode", '"client"')  # (a router routes between clients and peers)
        peer = zenoh.open(conf)
        stop = threading.Event()
        tokens = [peer.liveliness().declare_token(proto.key_alive(r)) for r in HOSTILE_RIGS]
        fakes = [(proto.key_status(r), proto.encode(msgspec.structs.replace(
            real, rig=r, plant=HOSTILE_TEXT, operator=HOSTILE_TEXT, faults=[HOSTILE_TEXT],
            notes=[HOSTILE_TEXT], knowledge=HOSTILE_TEXT, verdict=judged,
            watchdog=HOSTILE_TEXT))) for r in HOSTILE_RIGS]

        def keep_putting() -> None:
            while not stop.wait(0.2):
                for key, payload in fakes:
                    peer.put(key, payload)

        putter = threading.Thread(target=keep_putting, name="hostile-peer", daemon=True)
        putter.start()
        try:
            dopts = DashboardOptions(connect=(router,), rig_name="rig1", port=free_port(),
                                     verbose=False, fleet=True, recordings_dir=recordings)
            with Dashboard(dopts) as dash:
                mon = dash._fleet_monitor
                assert mon is not None
                want = sorted(["rig1", *HOSTILE_RIGS])
                wait_for(lambda: sorted(r.rig for r in mon.rows() if r.operator or r.mode) == want,
                      CONTROLLER_START_S, f"the rigs never showed: {mon.rows()}")
                yield {"dash": dash}
        finally:
            stop.set()
            putter.join(5.0)
            for t in tokens:
                t.undeclare()
            peer.close()


SHOWS_JS = """([sel, t]) => Array.from(document.querySelectorAll(sel)).some(
  e => e.innerText.includes(t))"""


def _shows(page: Any, selector: str, text: str) -> None:
    """Wait until an element of `selector` shows `text` (as text: what a user reads)."""
    try:
        page.wait_for_function(SHOWS_JS, arg=[selector, text], timeout=60_000, polling=100)
    except Exception:
        print("SHOWN", selector, page.evaluate("(s) => Array.from(document.querySelectorAll(s))"
                                               ".map(e => e.innerText)", selector))
        raise


def _tab(page: Any, name: str) -> None:
    page.get_by_role("tab", name=name).click()


def test_hostile_names_run_no_script_and_show_as_text(hostile: dict[str, Any],
                                                       artifacts: Path,
                                                       chromium_browser: Any) -> None:
    dash = hostile["dash"]
    dialogs: list[str] = []
    with contextlib.closing(chromium_browser.new_context(viewport=VIEWPORT)) as context:
        page = context.new_page()
        try:

            def on_dialog(d: Any) -> None:
                dialogs.append(d.message)
                d.dismiss()

            page.on("dialog", on_dialog)
            page.goto(dash.url, wait_until="domcontentloaded", timeout=FIRST_LOAD_S * 1000)
            page.wait_for_selector(".dt-banner", timeout=FIRST_LOAD_S * 1000)

            # Main view: the knowledge source in the banner and the verdict's "judged on".
            _shows(page, ".dt-banner", HOSTILE_TEXT)
            _shows(page, ".dt-knowledge", HOSTILE_TEXT)

            # Fleet: one row per rig, its name shown and in data-rig letter for letter.
            _tab(page, "Fleet")
            page.wait_for_function("(n) => document.querySelectorAll('.dt-fleet-row').length"
                                   " === n", arg=1 + len(HOSTILE_RIGS), timeout=60_000)
            rows = page.evaluate("() => Array.from(document.querySelectorAll('.dt-fleet-row'))"
                                 ".map(r => [r.dataset.rig, r.cells[0].innerText, "
                                 "r.innerText, r.attributes.length])")
            assert sorted(r[0] for r in rows) == sorted(["rig1", *HOSTILE_RIGS])
            for rig, first_cell, text, n_attributes in rows:
                assert first_cell.startswith(rig), (rig, first_cell)
                assert n_attributes == 2, (rig, n_attributes)  # class and data-rig, no more
                if rig != "rig1":
                    assert HOSTILE_TEXT in text, text  # lease holder and faults
            # Hover every row, as a user's mouse does (the table is redrawn at 2 Hz, so the
            # events go to whatever element is drawn now, every element of every row).
            page.evaluate("() => document.querySelectorAll('.dt-fleet-row, .dt-fleet-row *')"
                          ".forEach(e => ['mouseover', 'mouseenter', 'click'].forEach("
                          "k => e.dispatchEvent(new MouseEvent(k, {bubbles: true}))))")
            spots = page.evaluate("() => Array.from(document.querySelectorAll('.dt-fleet-row "
                                  "td')).map(e => e.getBoundingClientRect()).filter("
                                  "b => b.width > 0).map(b => [b.x + b.width / 2, "
                                  "b.y + b.height / 2])")
            assert len(spots) >= 7 * len(rows), spots  # every cell drawn
            for x, y in spots:
                page.mouse.move(x, y)
            page.screenshot(path=str(artifacts / "hostile_fleet.png"))

            # History: drawn after the hostile client's apply (its "who" is the controller's
            # name for the sender, `local` here, an authenticated user name with --auth: the
            # claimed client name never reaches this table).
            _tab(page, "History")
            _shows(page, ".dt-history", "local")

            # Recordings: the unreadable file, named with a payload, listed as such.
            _tab(page, "Recordings")
            page.wait_for_function(
                "(t) => Array.from(document.querySelectorAll('div')).some("
                "d => d.innerText.startsWith(t + ':'))", arg=HOSTILE_FILE, timeout=60_000)
            page.screenshot(path=str(artifacts / "hostile_recordings.png"))

            # Give any injected handler (onerror of an image) a chance to have run: a round
            # trip through the page after every view was drawn and hovered.
            _tab(page, "Tune")
            page.wait_for_function("() => document.readyState === 'complete'")
            assert page.evaluate(PWNED_JS) == [None]
            assert dialogs == []
            scripts = page.evaluate(
                "() => Array.from(document.querySelectorAll('script'))"
                ".filter(s => s.textContent.includes('__pwned')).length")
            assert scripts == 0
        except Exception:
            page.screenshot(path=str(artifacts / "hostile_failed.png"))
            raise
    # What the server sent: the payloads as text, never as markup.
    assert dash.fleet is not None
    assert "<img src=x" not in dash.fleet.table.content

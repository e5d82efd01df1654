"""Export and the view in the URL (issue 13 item 6), in headless Chromium against a real
controller: what the user gets.

- CSV of a Bode chart: the button under the chart -> a download -> its columns and values are
  the chart's data on the dashboard.
- PNG of the same chart: a valid PNG of the chart as drawn (its size, its curves' colour);
  PNG of the Nyquist view (SVG).
- The URL keeps the view: the selected tabs go into the URL; the page opened anew (another
  browser context: no cookie, nothing remembered) with that URL selects the same tabs.
- A raw websocket client (viser's protocol, no page): whatever an Export press carries, it
  gets only the CSV of that chart, only for the client that pressed; another client's row
  cannot be pressed.
"""

from __future__ import annotations

import csv
import io
import math
import time
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pytest
import zstandard
from conftest import FIRST_LOAD_S

from controller.client import ControllerClient
from server.charts import BODE_CHARTS, LIVE_CHARTS
from server.dashboard.app import Dashboard
from server.export import export_filename
from server.panels.widgets import EXPORT_LABEL

pytestmark = pytest.mark.browser

LOOP_MAG = next(s for s in BODE_CHARTS if s.key == "loop_mag")
ERROR = next(s for s in LIVE_CHARTS if s.key == "error")
#: The candidate's colour in the Bode charts (charts.CANDIDATE), as RGB.
CANDIDATE_RGB = (0x1F, 0x77, 0xB4)




def _export_button(page: Any, title: str, label: str) -> Any:
    """The `label` button in the Export row under the chart titled `title`."""
    return page.locator(
        f"xpath=//div[contains(@class,'u-title') and normalize-space(.)='{title}']"
        "/ancestor::div[contains(@class,'uplot-container')][1]/parent::*"
        f"/following-sibling::*[1]//button[normalize-space(.)='{label}']")


def _page_client(dashboard: Dashboard) -> Any:
    clients = list(dashboard.server.get_clients().values())
    assert len(clients) == 1, f"{len(clients)} browsers: the page alone expected"
    return clients[0]


def _ready(page: Any, dashboard: Dashboard) -> Any:
    """The page's candidate panel, once its charts are on the controller's knowledge."""
    page.wait_for_selector(".dt-verdict >> text=/plant knowledge v[1-9]/", timeout=30_000)
    panel = dashboard.panel_of(_page_client(dashboard))
    assert panel is not None
    assert panel.wait_idle(15.0) and panel.wait_preview_idle(30.0)
    return panel


def test_csv_of_a_bode_chart_is_the_charts_data(
    page: Any, dashboard: Dashboard, artifacts: Path
) -> None:
    panel = _ready(page, dashboard)
    button = _export_button(page, LOOP_MAG.title, "CSV")
    button.wait_for(timeout=15_000)
    button.scroll_into_view_if_needed()
    page.screenshot(path=str(artifacts / "export_rows.png"))
    before = [np.array(c) for c in panel._charts["loop_mag"].data]
    with page.expect_download(timeout=15_000) as got:
        button.click()
    dl = got.value
    after = [np.array(c) for c in panel._charts["loop_mag"].data]
    assert all(np.array_equal(a, b, equal_nan=True) for a, b in zip(before, after, strict=True)
               ), "the chart changed while it was exported: nothing to compare with"
    assert dl.suggested_filename == export_filename(LOOP_MAG, "csv")
    text = Path(dl.path()).read_text(encoding="utf-8")
    (artifacts / "export_loop_mag.csv").write_text(text)
    rows = list(csv.reader(io.StringIO(text)))
    header, body = rows[0], rows[1:]

    # One column per series of the chart the user sees, headed by its label (and unit).
    labels = page.evaluate("""(title) => {
      const ups = Object.values(window.__viserTestpoints?.uplots || {});
      const u = ups.find(u => u.chart.root.querySelector('.u-title')?.textContent === title);
      return u ? u.chart.series.map(s => s.label) : null;
    }""", LOOP_MAG.title)
    assert labels is not None and len(header) == len(labels) == len(before)
    assert all(h.startswith(str(lab)) for h, lab in zip(header, labels, strict=True)), header
    assert header[0] == "f (Hz)" and header[1] == "|L| candidate (dB)"

    # Every value is the dashboard's; an empty cell is a point the chart does not have (NaN:
    # the margin marks are NaN but at their two points).
    assert len(body) == len(before[0]) > 100
    for j, col in enumerate(before):
        cells = [r[j] for r in body]
        for i, (cell, v) in enumerate(zip(cells, col, strict=True)):
            if cell == "":
                assert math.isnan(v), (header[j], i, v)
            else:
                assert math.isclose(float(cell), v, rel_tol=1e-12, abs_tol=1e-300), (
                    header[j], i, cell, v)
    # The curves are there: |L| of the candidate is finite over the whole grid.
    assert all(r[1] != "" for r in body)


def _png(blob: bytes) -> np.ndarray:
    """RGB pixels of a PNG, decoded by Pillow (which checks the chunks' CRCs)."""
    from PIL import Image

    assert blob[:8] == b"\x89PNG\r\n\x1a\n"
    Image.open(io.BytesIO(blob)).verify()
    return np.asarray(Image.open(io.BytesIO(blob)).convert("RGB"))


def test_png_of_a_bode_chart_is_the_chart_as_drawn(
    page: Any, dashboard: Dashboard, artifacts: Path
) -> None:
    _ready(page, dashboard)
    button = _export_button(page, LOOP_MAG.title, "PNG")
    button.wait_for(timeout=15_000)  # the page script put it beside CSV
    canvas = page.evaluate("""(title) => {
      const ups = Object.values(window.__viserTestpoints?.uplots || {});
      const u = ups.find(u => u.chart.root.querySelector('.u-title')?.textContent === title);
      const c = u.chart.root.querySelector('canvas');
      const r = c.getBoundingClientRect();  // CSS size (what the page script reads)
      return [c.width, c.height, parseFloat(c.style.width) || r.width,
              parseFloat(c.style.height) || r.height];
    }""", LOOP_MAG.title)
    with page.expect_download(timeout=15_000) as got:
        button.click()
    dl = got.value
    assert dl.suggested_filename == export_filename(LOOP_MAG, "png")  # the CSV's stem
    blob = Path(dl.path()).read_bytes()
    (artifacts / "export_loop_mag.png").write_bytes(blob)
    assert len(blob) > 5_000
    px = _png(blob)
    height, width, _ = px.shape
    # Print resolution: the chart drawn again at 3 pixels per CSS pixel (at least 1800 px
    # wide; it was the screen's 1 px per CSS px here), the title above and the legend below.
    scale = max(3.0, 1800.0 / canvas[2])
    assert width >= 1800 and abs(width - round(canvas[2] * scale)) <= 1, (width, canvas)
    assert height > canvas[3] * scale + 20
    # The page's chart is drawn back at its own size.
    after = page.evaluate("""(title) => {
      const ups = Object.values(window.__viserTestpoints?.uplots || {});
      const u = ups.find(u => u.chart.root.querySelector('.u-title')?.textContent === title);
      const c = u.chart.root.querySelector('canvas');
      return [c.width, c.height];
    }""", LOOP_MAG.title)
    assert after == canvas[:2]
    colours = np.unique(px.reshape(-1, 3), axis=0)
    assert len(colours) > 20  # curves, grid, text: not a blank image
    background = px[1, 1]
    share = float(np.mean(np.any(px != background, axis=2)))
    assert 0.01 < share < 0.9, share
    # The candidate's curve is drawn: pixels of its colour (anti-aliasing aside).
    near = np.all(np.abs(px.astype(int) - CANDIDATE_RGB) <= 12, axis=2)
    assert near.sum() > 100, near.sum()


def test_png_of_the_nyquist_view(page: Any, dashboard: Dashboard, artifacts: Path) -> None:
    """The Nyquist view is SVG, not uPlot: its own PNG button, the same kind of file."""
    _ready(page, dashboard)
    try:
        page.get_by_role("tab", name="Nyquist", exact=True).click()  # the Bode tab's sub-tab
        page.wait_for_selector(".dt-nyquist polyline.dt-nyq-cand", state="attached",
                               timeout=20_000)
        # The views as laid out on the screen (with and without the DOB), at print resolution:
        # 3 pixels per CSS pixel, at least 1800 wide.
        size = page.evaluate("""() => {
          const rs = [...document.querySelectorAll('.dt-nyquist-box svg')]
            .map(g => g.getBoundingClientRect());
          const k = Math.max(3, 1800 / (Math.max(...rs.map(r => r.right))
                                        - Math.min(...rs.map(r => r.left))));
          return [Math.max(...rs.map(r => r.bottom)) - Math.min(...rs.map(r => r.top)),
                  Math.max(...rs.map(r => r.right)) - Math.min(...rs.map(r => r.left))]
            .map(v => Math.round(v * k));
        }""")
        button = page.locator(".dt-png-nyquist")
        button.wait_for(timeout=15_000)
        with page.expect_download(timeout=60_000) as got:
            button.click()
        dl = got.value
        assert dl.suggested_filename == "dobtune-nyquist-speed-loop.png"
        blob = Path(dl.path()).read_bytes()
        (artifacts / "export_nyquist.png").write_bytes(blob)
        px = _png(blob)
        assert list(px.shape[:2]) == size and size[1] >= 1800
        assert len(np.unique(px.reshape(-1, 3), axis=0)) > 20
        near = np.all(np.abs(px.astype(int) - CANDIDATE_RGB) <= 12, axis=2)
        assert near.sum() > 30, near.sum()  # the candidate's loop is drawn
    finally:  # back to the other tests' view, also after a failure
        page.get_by_role("tab", name="Decide", exact=True).click()


def _selected_tabs(page: Any) -> list[str]:
    return list(page.evaluate(
        "() => [...document.querySelectorAll('[data-dock-strip] [role=tab]')]"
        ".filter(t => t.getAttribute('aria-selected') === 'true').map(t => t.title)"))


def test_the_url_keeps_the_selected_tabs(page: Any, dashboard: Dashboard, artifacts: Path
                                         ) -> None:
    page.get_by_role("tab", name="Live traces").click()
    page.get_by_role("tab", name="Live", exact=True).click()
    page.wait_for_function(
        "() => location.hash.includes('tab=Live&') && location.hash.includes('plot=Live+traces')",
        timeout=FIRST_LOAD_S * 1000)
    url = page.url
    # the token stays in the query string, once (viser's unescaped websocket URL carried a
    # second copy beside the page's own)
    assert url.split("#")[0].count("token=") == 1, url

    other = page.context.browser.new_context(viewport={"width": 1600, "height": 1000})
    try:
        fresh = other.new_page()
        t0 = time.monotonic()
        fresh.goto(url, wait_until="domcontentloaded", timeout=FIRST_LOAD_S * 1000)
        fresh.wait_for_function("""() => {
          const on = [...document.querySelectorAll('[data-dock-strip] [role=tab]')]
            .filter(t => t.getAttribute('aria-selected') === 'true').map(t => t.title);
          return on.includes('Live') && on.includes('Live traces');
        }""", timeout=FIRST_LOAD_S * 1000)
        restored_s = time.monotonic() - t0
        print(f"tabs from the URL selected {restored_s:.2f} s after the page was opened")
        on = _selected_tabs(fresh)
        assert "Tune" not in on and "Bode" not in on, on
        # What is shown is the Live tab's content and the live traces.
        fresh.get_by_role("button", name="Set trajectory").wait_for(timeout=FIRST_LOAD_S * 1000)
        fresh.screenshot(path=str(artifacts / "export_url_view.png"),
                         timeout=FIRST_LOAD_S * 1000)
        fresh.wait_for_function("""(title) => [...document.querySelectorAll('.u-title')].some(
          t => t.textContent === title && t.getBoundingClientRect().width > 0)""",
                                arg=ERROR.title, timeout=FIRST_LOAD_S * 1000)
        # The URL still says so (viser rewrites the address when it starts).
        fresh.wait_for_function("(h) => location.hash === h", arg="#" + url.split("#")[1],
                                timeout=FIRST_LOAD_S * 1000)
        fresh.screenshot(path=str(artifacts / "export_url_view.png"),
                         timeout=FIRST_LOAD_S * 1000)
    finally:
        other.close()
        # Back to the tabs the other tests expect (also after a failure: the module's later
        # tests read the Tune tab).
        page.get_by_role("tab", name="Bode").click()
        page.get_by_role("tab", name="Tune").click()
    page.wait_for_function("() => location.hash === '#tab=Tune&plot=Bode&bode=Decide'",
                           timeout=FIRST_LOAD_S * 1000)


# -- a raw client ------------------------------------------------------------------------------


class RawClient:
    """viser's websocket protocol by hand: the messages it is sent (decoded), and GUI
    updates it sends as a browser would (or as a forger would)."""

    def __init__(self, dashboard: Dashboard) -> None:
        import viser
        from websockets.sync.client import connect

        host = f"127.0.0.1:{dashboard.server.get_port()}"
        self.ws = connect(
            f"ws://{host}/?token={dashboard.access.token}", open_timeout=30, max_size=None,
            ping_interval=None,
            additional_headers={"Origin": f"http://{host}"},
            subprotocols=[f"viser-v{viser.__version__}"],  # type: ignore[list-item]
        )
        self.messages: list[dict[str, Any]] = []
        self.files: list[tuple[str, bytes]] = []
        self._parts: dict[str, list[bytes]] = {}
        self._names: dict[str, tuple[str, int]] = {}
        self._zstd = zstandard.ZstdDecompressor()
        # viser counts a client as connected (and the dashboard builds its candidate panel)
        # at its first camera report, as a page sends it.
        self.ws.send(msgspec.msgpack.encode({
            "type": "ViewerCameraMessage", "wxyz": (1.0, 0.0, 0.0, 0.0),
            "position": (1.0, 1.0, 1.0), "fov": 1.0, "near": 0.01, "far": 100.0,
            "image_height": 600, "image_width": 800, "look_at": (0.0, 0.0, 0.0),
            "up_direction": (0.0, 0.0, 1.0)}))

    def close(self) -> None:
        self.ws.close()

    def _frame(self, raw: bytes) -> None:
        n_inner = int.from_bytes(raw[0:8], "little")
        n_comp = int.from_bytes(raw[8:16], "little")
        inner = self._zstd.decompress(raw[16:16 + n_comp], max_output_size=n_inner)
        for m in msgspec.msgpack.decode(inner)["messages"]:
            self.messages.append(m)
            if m["type"] == "FileTransferStartDownload":
                self._names[m["transfer_uuid"]] = (m["filename"], m["part_count"])
                self._parts[m["transfer_uuid"]] = []
            elif m["type"] == "FileTransferPart":
                parts = self._parts[m["transfer_uuid"]]
                parts.append(bytes(m["content"]))
                name, count = self._names[m["transfer_uuid"]]
                if len(parts) == count:
                    self.files.append((name, b"".join(parts)))

    def pump_until(self, cond: Any, timeout_s: float, what: str) -> None:
        end = time.monotonic() + timeout_s
        while not cond():
            left = end - time.monotonic()
            assert left > 0, f"{what}; sent so far: {self.summary()}"
            try:
                self._frame(self.ws.recv(timeout=min(left, 1.0)))
            except TimeoutError:
                continue

    def summary(self) -> str:
        kinds: dict[str, int] = {}
        for m in self.messages:
            kinds[m["type"]] = kinds.get(m["type"], 0) + 1
        titles = [m["props"].get("title") for m in self.messages
                  if m["type"] == "GuiUplotMessage"]
        return f"{kinds}, charts {titles}"

    def export_row(self, title: str) -> str:
        """The uuid of the Export row under the chart titled `title` (the row follows its
        chart in the same container)."""
        charts = [m for m in self.messages if m["type"] == "GuiUplotMessage"
                  and m["props"].get("title") == title]
        rows = [m for m in self.messages if m["type"] == "GuiButtonGroupMessage"
                and m["props"].get("label") == EXPORT_LABEL]
        assert charts, f"no chart {title!r} sent to this client"
        c = charts[-1]
        after = [r for r in rows if r["container_uuid"] == c["container_uuid"]
                 and r["props"]["order"] > c["props"]["order"]]
        assert after, f"no Export row under {title!r}"
        return str(min(after, key=lambda r: r["props"]["order"])["uuid"])

    def press(self, uuid: str, value: Any) -> None:
        self.ws.send(msgspec.msgpack.encode(
            {"type": "GuiUpdateMessage", "uuid": uuid, "updates": {"value": value}}))


def _has_row(c: RawClient, title: str) -> bool:
    """`c` was sent the chart titled `title` and its Export row."""
    try:
        c.export_row(title)
    except AssertionError:
        return False
    return True


def test_a_csv_press_gets_only_that_charts_data_for_the_client_that_pressed(
    page: Any, dashboard: Dashboard, probe: ControllerClient
) -> None:
    page_downloads: list[Any] = []

    def on_download(d: Any) -> None:
        page_downloads.append(d)

    page.on("download", on_download)
    config_before = probe.get_config()
    clients: list[RawClient] = []
    try:
        # One after the other: two browsers connecting at the same instant break the
        # dashboard's candidate panels (app.py panel_in enters the shared Bode tab's context
        # from two threads: RuntimeError, the second browser gets no candidate panel).
        for _ in range(2):
            c = RawClient(dashboard)
            clients.append(c)
            c.pump_until(lambda c=c: _has_row(c, LOOP_MAG.title) and _has_row(
                c, ERROR.title), 60.0, "the raw client got no charts with Export rows")
        a, b = clients
        a_bode, b_bode = a.export_row(LOOP_MAG.title), b.export_row(LOOP_MAG.title)
        assert a_bode != b_bode  # each browser its own candidate charts
        live_row = a.export_row(ERROR.title)
        assert live_row == b.export_row(ERROR.title)  # the live charts are shared

        # A forges presses of another client's row: nothing happens for anyone.
        assert dashboard.messages is not None
        refused = dashboard.messages.refused
        a.press(b_bode, "CSV")
        # A forges values on its own rows: refused before viser sees them (not one of the
        # row's options: server/message_gate.py); its CSV press is this chart's CSV.
        forged = ["PNG", "../../../etc/passwd", "", 12345, "x" * 10_000]
        for v in (*forged, "CSV"):
            a.press(a_bode, v)
        a.press(live_row, "CSV")
        a.pump_until(lambda: len(a.files) == 2, 30.0, "A's files did not come")
        assert dashboard.messages.refused == refused + 1 + len(forged)
        names = [n for n, _ in a.files]
        assert sorted(names) == sorted([export_filename(LOOP_MAG, "csv"),
                                        export_filename(ERROR, "csv")])
        for name, content in a.files:
            rows = list(csv.reader(io.StringIO(content.decode("utf-8"))))
            spec = LOOP_MAG if name == export_filename(LOOP_MAG, "csv") else ERROR
            assert len(rows[0]) == len(spec.series) and rows[0][0] in ("f (Hz)", "t (s)")
            assert len(rows) > 2 and all(len(r) == len(spec.series) for r in rows)
            values = np.array([float(x) for r in rows[1:] for x in r if x])  # numbers only
            assert np.isfinite(values).sum() > len(rows)

        # B presses its own row once: it gets one file, its own (no file of A's, and A's
        # forged press of B's row gave B nothing).
        b.press(b_bode, "CSV")
        b.pump_until(lambda: len(b.files) >= 1, 30.0, "B's file did not come")
        assert [n for n, _ in b.files] == [export_filename(LOOP_MAG, "csv")]
        assert not [m for m in b.messages if m["type"] == "FileTransferStartDownload"][1:]
        page.evaluate("1")  # let Playwright deliver the page's events
        assert page_downloads == []
    finally:
        for c in clients:
            c.close()
        page.remove_listener("download", on_download)
    after = probe.get_config()
    assert after.version == config_before.version and after.config == config_before.config


def test_png_of_a_long_titled_chart_has_the_whole_title_in_its_name(
    page: Any, dashboard: Dashboard
) -> None:
    """The browser's download name of the rejection chart's PNG carries its whole title (the
    name was cut at 48 characters)."""
    from server.charts import BODE_CHARTS

    _ready(page, dashboard)
    page.get_by_role("tab", name="Bode", exact=True).click()
    page.get_by_role("tab", name="Decide", exact=True).click()
    spec = next(s for s in BODE_CHARTS if s.key == "rejection")
    button = _export_button(page, spec.title, "PNG")
    button.wait_for(timeout=15_000)
    button.scroll_into_view_if_needed(timeout=15_000)
    with page.expect_download(timeout=15_000) as got:
        button.click()
    name = got.value.suggested_filename
    assert name == ("dobtune-dob-rejection-gain-tracking-error-without-dob-with-dob-article-eq-23-"
                    "0-db-where-the-dob-helps-0-db-where-it-costs-waterbed.png")
    assert name == export_filename(spec, "png")  # the CSV's stem


def test_png_of_a_narrow_chart_has_its_whole_title(page: Any, dashboard: Dashboard,
                                                    artifacts: Path) -> None:
    """The recordings overlay sat in the narrow sidebar; its one-line title ran off both
    edges of the PNG. Wrapped, the title's ink keeps off the image's left and right edges (the
    overlay is now in the plots panel's Compare runs tab: the same check there)."""
    from server.panels.recordings import COMPARE_TAB, OVERLAY_CHART

    _ready(page, dashboard)
    page.get_by_role("tab", name=COMPARE_TAB, exact=True).click()
    button = _export_button(page, OVERLAY_CHART.title, "PNG")
    button.wait_for(timeout=30_000)
    with page.expect_download(timeout=15_000) as got:
        button.click()
    blob = Path(got.value.path()).read_bytes()
    (artifacts / "export_overlay.png").write_bytes(blob)
    px = _png(blob).astype(int)
    top = px[: px.shape[0] // 6]  # the title band (the chart below is taller than the title)
    ink = (top.sum(axis=2) < 3 * 160)  # dark text on the light background
    assert ink.any(), "no title drawn"
    edge = max(4, px.shape[1] // 100)
    assert not ink[:, :edge].any() and not ink[:, -edge:].any(), "the title runs off the image"

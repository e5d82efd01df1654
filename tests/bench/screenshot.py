"""The README's screenshot of the dashboard, made anew from the running product.

    .venv/bin/python tests/bench/screenshot.py [--out docs/dashboard.png] [--tabs docs/screens]

A simulated controller and the dashboard, headless Chromium (Debian's), the live traces
rolling; the page as a user sees it after ~10 s.
"""

from __future__ import annotations

import argparse
import socket
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from server.app import Dashboard, DashboardOptions  # noqa: E402
from server.demo import controller_process  # noqa: E402


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


#: (controls tab, plots tab, file name) of --tabs: every tab of the controls, each beside the
#: plots tab it goes with.
TABS = (("Tune", "Bode", "tab_tune.png"), ("Live", "Live traces", "tab_live.png"),
        ("Identify", "Identify", "tab_identify.png"), ("History", "Bode", "tab_history.png"),
        ("Recordings", "Compare runs", "tab_recordings.png"), ("Help", "Bode", "tab_help.png"))


def every_tab(page: Any, out_dir: Path) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    for controls, plots, name in TABS:
        page.get_by_role("tab", name=controls, exact=True).first.click()
        # Identify names a controls tab and a plots tab: the plots one is the last.
        page.get_by_role("tab", name=plots, exact=True).last.click()
        page.wait_for_timeout(2500)  # charts drawn, texts refreshed
        page.screenshot(path=str(out_dir / name))
        print(f"wrote {out_dir / name}")


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "dashboard.png")
    ap.add_argument("--tabs", type=Path, default=None, metavar="DIR",
                    help="also a screenshot of every tab into DIR (tab_<name>.png)")
    args = ap.parse_args()
    from playwright.sync_api import sync_playwright

    ep = f"tcp/127.0.0.1:{free_port()}"
    with controller_process(ep, "demo"), Dashboard(DashboardOptions(
            connect=(ep,), rig_name="demo", port=free_port(), verbose=False)) as dash:
        deadline = time.monotonic() + 60
        while not dash.client.connected:
            if time.monotonic() > deadline:
                raise SystemExit("the controller did not come up")
            time.sleep(0.1)
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path="/usr/bin/chromium",
                                        args=["--no-sandbox", "--disable-gpu"])
            page = browser.new_page(viewport={"width": 1600, "height": 1000})
            page.set_default_timeout(180_000)  # a loaded machine (load 20: 30-50 s stalls)
            page.goto(dash.url, wait_until="domcontentloaded", timeout=60_000)
            page.wait_for_selector(".dt-banner.dt-ok", timeout=60_000)
            page.get_by_role("tab", name="Live traces").click()
            page.wait_for_timeout(10_000)  # let the traces fill their window
            # The software-WebGL notice is the headless browser's, not the product's.
            notice = page.get_by_text("Software WebGL rendering detected")
            if notice.count():
                page.locator("button.mantine-Notification-closeButton").first.click()
            args.out.parent.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(args.out))
            if args.tabs is not None:
                every_tab(page, args.tabs)
            browser.close()
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The README's screenshot of the dashboard, made anew from the running product.

    .venv/bin/python tests/bench/screenshot.py [--out docs/dashboard.png] [--tabs docs/screens]

A simulated controller and the dashboard, headless Chromium (Debian's), the live traces
rolling; the page as a user sees it after ~10 s. With --tabs, two runs of the simulated rig are
recorded first (RUN_S each: the active configuration, then a Q cut-off of B_CUTOFF_HZ applied
through the gate, then the first configuration applied back), so that the Recordings tab lists
them and Compare runs compares them.
"""

from __future__ import annotations

import argparse
import socket
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from controller.client import ClientOptions, ControllerClient  # noqa: E402
from controller.client.recorder import Recorder, RecordOptions  # noqa: E402
from server.dashboard.app import Dashboard, DashboardOptions  # noqa: E402
from server.dashboard.demo import controller_process  # noqa: E402

#: The length of each recorded run (the demo's trajectory repeats every 10 s).
RUN_S = 14.0
#: Run B's Q cut-off.
B_CUTOFF_HZ = 2.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


COMPARE = "Compare runs"
#: (controls tab, plots tab, file name) of --tabs: every tab of the controls, each beside the
#: plots tab it goes with.
TABS = (("Tune", "Bode", "tab_tune.png"), ("Live", "Live traces", "tab_live.png"),
        ("Identify", "Identify", "tab_identify.png"), ("History", "Bode", "tab_history.png"),
        ("Recordings", COMPARE, "tab_recordings.png"), ("Help", "Bode", "tab_help.png"))


def record_two_runs(ep: str, out_dir: Path) -> tuple[str, str]:
    """Run A on the active configuration, run B with the Q cut-off at B_CUTOFF_HZ (applied
    through the gate); the first configuration applied back. The two files' names."""
    out_dir.mkdir(parents=True, exist_ok=True)
    names = []
    with ControllerClient(ClientOptions(connect=(ep,), rig_name="demo",
                                        client_name="screenshot")) as c:
        deadline = time.monotonic() + 180  # the controller's start on a loaded machine
        while not c.connected:
            if time.monotonic() > deadline:
                raise SystemExit("the controller did not come up")
            time.sleep(0.1)
        start = c.get_config()
        for tag, cfg in (("A", start.config), ("B", start.config.with_(q_cutoff_hz=B_CUTOFF_HZ))):
            if cfg != c.get_config().config:
                reply = c.apply(cfg, confirm=True)
                if not reply.accepted:
                    raise SystemExit(f"run {tag}: not applied: {reply.reasons}")
            path = out_dir / f"run_{tag}_q{cfg.q_cutoff_hz:g}hz.mcap"
            print(Recorder(RecordOptions(connect=(ep,), out=path, rig_name="demo",
                                         duration_s=RUN_S)).run().summary())
            names.append(path.name)
        c.apply(start.config, confirm=True)
    return names[0], names[1]


def compare(page: Any, a: str, b: str) -> None:
    """Pick A and B in the Compare runs tab and press Compare, as a user does."""
    for label, name in (("A (before)", a), ("B (after)", b)):
        page.get_by_label(label, exact=True).click()
        page.get_by_role("option", name=name, exact=True).click()
    page.get_by_role("button", name="Compare", exact=True).click()
    page.wait_for_function("(b) => document.querySelector('.dt-compare')?.innerText"
                           ".includes(b)", arg=b)


def every_tab(page: Any, out_dir: Path, runs: tuple[str, str] | None = None) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    for controls, plots, name in TABS:
        page.get_by_role("tab", name=controls, exact=True).first.click()
        # Identify names a controls tab and a plots tab: the plots one is the last.
        page.get_by_role("tab", name=plots, exact=True).last.click()
        if plots == COMPARE and runs is not None:
            compare(page, *runs)
        page.wait_for_timeout(2500)  # charts drawn, texts refreshed
        page.screenshot(path=str(out_dir / name))
        print(f"wrote {out_dir / name}")


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "dashboard.png")
    ap.add_argument("--tabs", type=Path, default=None, metavar="DIR",
                    help="also a screenshot of every tab into DIR (tab_<name>.png)")
    args = ap.parse_args()

    ep = f"tcp/127.0.0.1:{free_port()}"
    with tempfile.TemporaryDirectory(prefix="dobtune-shots-") as tmp, \
            controller_process(ep, "demo"):
        runs = (record_two_runs(ep, Path(tmp)) if args.tabs is not None else None)
        shoot(args, ep, Path(tmp), runs)
    print(f"wrote {args.out}")
    return 0


def shoot(args: argparse.Namespace, ep: str, recordings: Path,
          runs: tuple[str, str] | None) -> None:
    from playwright.sync_api import sync_playwright

    with Dashboard(DashboardOptions(connect=(ep,), rig_name="demo", port=free_port(),
                                    verbose=False, recordings_dir=recordings)) as dash:
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
                every_tab(page, args.tabs, runs)
            browser.close()


if __name__ == "__main__":
    sys.exit(main())

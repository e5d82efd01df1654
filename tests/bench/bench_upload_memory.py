"""An upload that never completes, against a running dashboard: its memory (RSS) before, during
and after (issue 31 item 6: "an upload that never completes grows the dashboard by 300 MB in
5 s, kept after disconnect").

A dashboard (`dobtune dashboard`, one identity: every browser may upload, as an operator) and a
raw websocket client (tests/viser_raw.py) on its URL. The client announces a file of
`--declared-mb` to the Tune tab's upload button (Upload measured responses), then sends
`--part-kib` parts as fast as it can for `--seconds`, never the last one; then it closes its
connection. RSS of the dashboard's process from /proc: before, the peak during the attack and
the 2 s after it, and 3 s after the disconnect.

    .venv/bin/python tests/bench/bench_upload_memory.py [--tree DIR]

`--tree DIR`: run the dashboard of that source tree (e.g. an older commit's, from
`git archive`), for a before/after table.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from helpers import free_port  # noqa: E402
from viser_raw import RawViser  # noqa: E402

REPO = HERE.parents[1]
LABEL = "Upload measured responses (CSV)"


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    raise RuntimeError("no VmRSS")


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--tree", type=Path, default=None)
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--declared-mb", type=float, default=300.0)
    ap.add_argument("--part-kib", type=int, default=512)
    a = ap.parse_args()
    tree = a.tree or REPO
    with tempfile.TemporaryDirectory() as tmp:
        port = free_port()
        cmd = [sys.executable, "-m", "controller.cli.main", "dashboard",
               "--connect", f"tcp/127.0.0.1:{free_port()}", "--rig-name", "upload",
               "--port", str(port), "--recordings", f"{tmp}/rec",
               "--candidates", f"{tmp}/cand"]
        env = {**os.environ, "PYTHONPATH": str(tree), "PYTHONUNBUFFERED": "1"}
        proc = subprocess.Popen(cmd, cwd=tree, env=env, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True)
        try:
            url = ""
            assert proc.stdout is not None
            for line in proc.stdout:
                m = re.search(r"(http://\S+\?token=\S+)", line)
                if m:
                    url = m.group(1)
                    break
            assert url, "the dashboard printed no URL"
            raw = RawViser(url.replace("http://", "ws://"), origin=url.split("/?")[0])
            found: list[str] = []

            def upload_button() -> bool:
                for msg in raw.messages:
                    if (msg.get("type") == "GuiUploadButtonMessage"
                            and msg["props"]["label"] == LABEL):
                        found.append(msg["uuid"])
                        return True
                return False

            raw.pump_until(upload_button, 60.0, "no upload button")
            time.sleep(2.0)  # the start-up settles (a measurement, not a synchronisation)
            before = rss_mb(proc.pid)
            part = os.urandom(a.part_kib * 1024)
            declared = int(a.declared_mb * 1e6)
            n_parts = -(-declared // len(part))
            raw.send({"type": "FileTransferStartUpload", "source_component_uuid": found[0],
                      "transfer_uuid": "bench-upload", "filename": "big.csv",
                      "mime_type": "text/csv", "part_count": n_parts, "size_bytes": declared})
            peak, sent, t0 = before, 0, time.monotonic()
            while time.monotonic() - t0 < a.seconds and sent < n_parts - 1:
                raw.send({"type": "FileTransferPart", "source_component_uuid": found[0],
                          "transfer_uuid": "bench-upload", "part_index": sent, "content": part})
                sent += 1
                if sent % 16 == 0:
                    peak = max(peak, rss_mb(proc.pid))
            t_end = time.monotonic() + 2.0
            while time.monotonic() < t_end:
                peak = max(peak, rss_mb(proc.pid))
                time.sleep(0.1)
            held = rss_mb(proc.pid)
            raw.ws.close()
            time.sleep(3.0)
            after = rss_mb(proc.pid)
        finally:
            proc.terminate()
            proc.wait(30)
    print(f"tree: {tree}")
    print(f"sent {sent} parts of {a.part_kib} KiB ({sent * a.part_kib / 1024:.0f} MiB) in "
          f"{a.seconds:g} s, declared {a.declared_mb:g} MB")
    print("| RSS (MB) | before | peak (attack + 2 s) | 2 s after the attack | 3 s after "
          "disconnect |")
    print(f"| dashboard | {before:.0f} | {peak:.0f} | {held:.0f} | {after:.0f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

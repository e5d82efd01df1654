"""CI: build the wheel, install it into a fresh virtual environment and check that the installed
dashboard serves its page script (in the page) and its help texts (over its websocket).

    .venv/bin/python .ci/check_wheel.py

The fresh environment gets the project's dependencies from this interpreter's site-packages (a
.pth path line: not a site directory, so this checkout's editable install is not seen) and the
project only from the wheel; the dashboard runs from a temporary directory, away from the
source tree.
"""

from __future__ import annotations

import os
import re
import shutil
import site
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def main() -> int:
    tmp = Path(tempfile.mkdtemp(prefix="dobtune-wheel-"))
    try:
        src = tmp / "src"
        files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=ROOT,
                               capture_output=True, text=True, check=True).stdout.split()
        for f in files:
            if (ROOT / f).is_file():
                (src / f).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(ROOT / f, src / f)
        subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w",
                        str(tmp / "dist"), str(src)], check=True)
        wheel = next((tmp / "dist").glob("dobtune-*.whl"))
        env_dir = tmp / "fresh"
        venv.create(env_dir, with_pip=False)
        py = env_dir / "bin" / "python"
        fresh_site = Path(subprocess.run(
            [str(py), "-c", "import site; print(site.getsitepackages()[0])"],
            capture_output=True, text=True, check=True).stdout.strip())
        (fresh_site / "dobtune-deps.pth").write_text(site.getsitepackages()[0] + "\n")
        subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "-q",
                        "--no-deps", "--no-index", str(wheel)], check=True)
        help_line = next(x for x in (ROOT / "web_assets" / "help.md").read_text().splitlines()
                         if len(x) > 40)
        script = (ROOT / "web_assets" / "dashboard.js").read_text()
        script_line = next(x for x in script.splitlines() if len(x) > 40)
        port = free_port()
        run_dir = tmp / "run"
        run_dir.mkdir()
        env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
        dash = subprocess.Popen(
            [str(env_dir / "bin" / "dobtune"), "dashboard", "--port", str(port), "--connect",
             f"tcp/127.0.0.1:{free_port()}", "--rig-name", "wheel", "--recordings",
             str(run_dir)], cwd=run_dir, env=env, stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT, text=True)
        try:
            url = ""
            deadline = time.monotonic() + 120.0
            assert dash.stdout is not None
            while not url and time.monotonic() < deadline:
                line = dash.stdout.readline()
                if not line:
                    raise SystemExit(f"the installed dashboard exited ({dash.wait()})")
                m = re.search(r"(http://\S+\?token=\S+)", line)
                url = m.group(1) if m else ""
            if not url:
                raise SystemExit("no URL from the installed dashboard within 120 s")
            with urllib.request.urlopen(url, timeout=30) as r:
                page = r.read().decode()
            token = url.split("?token=", 1)[1]
            assert script_line in page, "the page has no page script (web_assets/dashboard.js)"
            print(f"wheel: the installed dashboard serves its page script ({wheel.name})")
            check_help(port, token, help_line)
            print("wheel: the installed dashboard serves its help texts")
        finally:
            dash.terminate()
            dash.wait(30)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


def check_help(port: int, token: str, help_line: str) -> None:
    """The help texts arrive over the dashboard's websocket (the shared GUI's markdown)."""
    import msgspec
    import viser
    import zstandard
    from websockets.sync.client import connect

    host = f"127.0.0.1:{port}"
    zstd = zstandard.ZstdDecompressor()
    with connect(f"ws://{host}/?token={token}", open_timeout=30, max_size=None,
                 ping_interval=None, additional_headers={"Origin": f"http://{host}"},
                 subprotocols=[f"viser-v{viser.__version__}"]) as ws:  # type: ignore[list-item]
        ws.send(msgspec.msgpack.encode({
            "type": "ViewerCameraMessage", "wxyz": (1.0, 0.0, 0.0, 0.0),
            "position": (1.0, 1.0, 1.0), "fov": 1.0, "near": 0.01, "far": 100.0,
            "image_height": 600, "image_width": 800, "look_at": (0.0, 0.0, 0.0),
            "up_direction": (0.0, 0.0, 1.0)}))
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline:
            raw = ws.recv(timeout=max(0.1, deadline - time.monotonic()))
            if not isinstance(raw, bytes):
                continue
            # viser's frame: inner size, compressed size, zstd(msgpack {"messages": [...]})
            n_inner, n_comp = (int.from_bytes(raw[i:i + 8], "little") for i in (0, 8))
            inner = zstd.decompress(raw[16:16 + n_comp], max_output_size=n_inner)
            for m in msgspec.msgpack.decode(inner)["messages"]:
                props = m.get("props") if isinstance(m, dict) else None
                if isinstance(props, dict) and help_line in str(props.get("_markdown", "")
                                                                + str(props.get("markdown", ""))
                                                                + str(props.get("content", ""))):
                    return
    raise SystemExit("the installed dashboard sent no help texts (web_assets/help.md)")


if __name__ == "__main__":
    sys.exit(main())

"""The watch started by `dobtune controller` beside its loop (`--no-watch`: not started): a
child process (`dobtune watch`, niced, its own interpreter: nothing of it runs in the loop's
process) started once the loop runs, stopped with the controller, and with `--parent-pid` so
that a controller killed outright leaves no watch behind. It connects to the controller's
first listen endpoint on loopback and keeps the rig's trend and prediction checks under the
controller's state directory (`<state>/trend`)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

__all__ = ["WatchChild", "loopback_endpoint"]


def loopback_endpoint(listen: str) -> str:
    """The endpoint to reach a controller listening on `listen` from this machine (a wildcard
    address becomes 127.0.0.1)."""
    for wildcard in ("0.0.0.0", "[::]"):
        if f"/{wildcard}:" in listen:
            return listen.replace(f"/{wildcard}:", "/127.0.0.1:")
    return listen


class WatchChild:
    def __init__(self, endpoint: str, rig_name: str, state_dir: Path,
                 disturbances: tuple[str, ...], log_level: str) -> None:
        code = ("import sys; from controller.cli.main import dobtune_main; "
                "sys.exit(dobtune_main(['watch', *sys.argv[1:]]))")
        dist = [a for d in (disturbances or ("none",)) for a in ("--disturbance", d)]
        self.command = [sys.executable, "-c", code, "--connect", endpoint,
                        "--rig-name", rig_name, "--trend-dir", str(state_dir / "trend"),
                        "--log-level", log_level, "--parent-pid", str(os.getpid()), *dist]
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        if self.proc is None:
            # Its own session: a Ctrl-C at the terminal (SIGINT to the foreground group)
            # reaches the controller, which stops the watch itself, not the watch mid-import.
            self.proc = subprocess.Popen(self.command, start_new_session=True)

    def stop(self, timeout_s: float = 10.0) -> int | None:
        """SIGTERM, then SIGKILL after `timeout_s`; its exit code (None: never started)."""
        if self.proc is None:
            return None
        self.proc.terminate()
        try:
            return self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return self.proc.wait(timeout_s)

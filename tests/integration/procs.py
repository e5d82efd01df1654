"""Helpers for tests that start real processes: a controller on a free loopback port, and a
Zenoh client (the test's own peer session: peer mode, explicit endpoint, no multicast).

Nothing here sleeps to synchronise: every wait is a condition polled until a deadline.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh
from helpers import free_port, port_is_free, spawn, wait_until

from controller import protocol as proto
from controller.client.controller_client import ClientOptions
from controller.client.session import SessionOptions, connect
from controller.core.config import LoopConfig

__all__ = ["APPLY_TIMEOUT_S", "REPO", "Client", "ControllerProcess", "free_port", "port_is_free",
           "start_controller", "wait_until"]

REPO = Path(__file__).resolve().parents[2]








@dataclass
class ControllerProcess:
    """A `python -m controller` child process (stdout/stderr captured to files)."""

    port: int
    rig: str
    state_dir: Path
    proc: subprocess.Popen[bytes]
    log_path: Path

    @property
    def endpoint(self) -> str:
        return f"tcp/127.0.0.1:{self.port}"

    def log(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")
        except OSError:
            return ""

    def stop(self, sig: int = signal.SIGINT, timeout_s: float = 10.0) -> int:
        """Send `sig`, wait for the exit (SIGKILL after the timeout); returns the exit code."""
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=timeout_s)
        return int(self.proc.returncode)


def start_controller(
    state_dir: Path,
    *,
    rig: str = "itest",
    port: int | None = None,
    extra_args: tuple[str, ...] = (),
    python_code: str | None = None,
    listen: bool = True,
    tree: Path | None = None,
    watch: bool = False,
) -> ControllerProcess:
    """Start a controller on 127.0.0.1:<free port> (`listen` False: none, for a controller
    behind an authenticating router). `python_code` replaces `-m controller` (for options the
    command line does not expose); it gets the same arguments in argv. `tree`: run the code of
    that source tree (an older commit's, for benchmarks) instead of this repository's. `watch`:
    with the watch the controller starts beside its loop (default: `--no-watch`)."""
    port = free_port() if port is None else port
    args = [
        *(("--listen", f"tcp/127.0.0.1:{port}") if listen else ()),
        "--rig-name",
        rig,
        "--state-dir",
        str(state_dir),
        *extra_args,
        # the watch beside the loop (`dobtune controller` starts it) only where a test asks:
        # (an older tree's controller has no such option)
        *(() if watch or tree is not None or python_code is not None else ("--no-watch",)),
    ]
    cmd = [sys.executable, "-m", "controller", *args]
    if python_code is not None:
        cmd = [sys.executable, "-c", python_code, *args]
    state_dir.mkdir(parents=True, exist_ok=True)
    log_path = state_dir.parent / f"controller-{rig}-{port}.log"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    if tree is not None:
        env["PYTHONPATH"] = str(tree)
    with open(log_path, "ab") as log:
        proc = spawn(cmd, cwd=tree or REPO, stdout=log, stderr=subprocess.STDOUT, env=env)
    return ControllerProcess(port=port, rig=rig, state_dir=state_dir, proc=proc, log_path=log_path)


class ClientError(AssertionError):
    pass


@dataclass
class StateCollector:
    """Every StateBatch received (decoded in the test thread, not in the callback)."""

    raw: list[tuple[float, bytes]] = field(default_factory=list)
    _decoded: list[tuple[float, proto.StateBatch]] = field(default_factory=list)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def on_sample(self, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        now = time.time()
        with self._lock:
            self.raw.append((now, data))

    def batches(self) -> list[tuple[float, proto.StateBatch]]:
        """(receive UNIX time, batch) for everything received so far, in arrival order."""
        with self._lock:
            new = self.raw[len(self._decoded) :]
        for t, data in new:
            self._decoded.append((t, proto.decode(data, proto.StateBatch)))
        return list(self._decoded)

    def clear(self) -> None:
        with self._lock:
            self.raw.clear()
            self._decoded.clear()

    def last_seq(self) -> int:
        b = self.batches()
        if not b:
            return -1
        last = b[-1][1]
        return last.seq0 + len(last.t_s) - 1

    def samples(self) -> dict[int, dict[str, Any]]:
        """seq -> {column: value, 'version', 'mode', 'recv_s'}."""
        out: dict[int, dict[str, Any]] = {}
        for t, b in self.batches():
            for i in range(len(b.t_s)):
                out[b.seq0 + i] = {
                    "t_s": b.t_s[i],
                    "ref_deg": b.ref_deg[i],
                    "pos_deg": b.pos_deg[i],
                    "command_deg_s": b.command_deg_s[i],
                    "d_hat_deg_s": b.d_hat_deg_s[i],
                    "version": b.config_version,
                    "mode": b.mode,
                    "recv_s": t,
                    "wall_s": b.epoch_s + b.t_s[i],
                }
        return out

    def wait_for_seq(self, seq: int, timeout_s: float) -> bool:
        return wait_until(lambda: self.last_seq() >= seq, timeout_s)


#: How long an apply may take before its reply (the dashboard's and `dobtune ctl`'s wait).
APPLY_TIMEOUT_S = ClientOptions().apply_timeout_s


class Client:
    """The test's own Zenoh peer connected to one controller."""

    def __init__(self, endpoint: str, rig: str, timeout_s: float = 5.0) -> None:
        self.endpoint = endpoint
        self.rig = rig
        self.timeout_s = timeout_s
        self._stack = contextlib.ExitStack()
        self.session: Any = None
        self._status: proto.Status | None = None
        self._status_count = 0
        self._status_lock = threading.Lock()

    def __enter__(self) -> Client:
        self.session = self._stack.enter_context(connect(SessionOptions(connect=(self.endpoint,))))
        sub = self.session.declare_subscriber(proto.key_status(self.rig), self._on_status)
        self._stack.callback(sub.undeclare)
        return self

    def __exit__(self, *exc: object) -> None:
        self._stack.close()

    def _on_status(self, sample: zenoh.Sample) -> None:
        try:
            st = proto.decode(sample.payload.to_bytes(), proto.Status)
        except proto.ProtocolError:
            return
        with self._status_lock:
            self._status = st
            self._status_count += 1

    # -- status ------------------------------------------------------------------------------

    def fresh_status(self, timeout_s: float = 5.0) -> proto.Status:
        """The next status published after this call."""
        with self._status_lock:
            n = self._status_count
        if not wait_until(lambda: self._status_count > n, timeout_s):
            raise ClientError(f"no status within {timeout_s} s")
        with self._status_lock:
            assert self._status is not None
            return self._status

    # -- subscriptions -----------------------------------------------------------------------

    @contextlib.contextmanager
    def state(self) -> Iterator[StateCollector]:
        col = StateCollector()
        sub = self.session.declare_subscriber(proto.key_state(self.rig), col.on_sample)
        try:
            yield col
        finally:
            sub.undeclare()

    # -- queries -----------------------------------------------------------------------------

    def query_raw(self, key: str, payload: bytes | None, timeout_s: float | None = None) -> bytes:
        t = self.timeout_s if timeout_s is None else timeout_s
        kw: dict[str, Any] = {"timeout": t}
        if payload is not None:
            kw["payload"] = payload
        for reply in self.session.get(key, **kw):
            if reply.ok is not None:
                data: bytes = reply.ok.payload.to_bytes()
                return data
            raise ClientError(f"error reply: {reply.err.payload.to_string()}")
        raise ClientError(f"no reply on {key} within {t} s")

    def config_raw(self, payload: bytes | None,
                   timeout_s: float | None = None) -> proto.ConfigReply:
        """A config request (waiting `timeout_s`, default the client's; an apply: pass
        APPLY_TIMEOUT_S, the gate may take over 5 s at load 20+)."""
        return proto.decode(self.query_raw(proto.key_config(self.rig), payload, timeout_s),
                            proto.ConfigReply)

    def command_raw(self, payload: bytes) -> proto.CommandReply:
        return proto.decode(
            self.query_raw(proto.key_command(self.rig), payload), proto.CommandReply
        )

    def get_config(self) -> proto.ConfigReply:
        return self.config_raw(proto.encode(proto.ConfigRequest(client="test")))

    def apply(self, candidate: LoopConfig) -> proto.ConfigReply:
        return self.config_raw(
            proto.encode(proto.ConfigRequest(candidate=candidate, client="test")), APPLY_TIMEOUT_S
        )

    def command(self, body: proto.CommandBody) -> proto.CommandReply:
        return self.command_raw(proto.encode(proto.Command(body=body, client="test")))

    def reset(self, estop_seq: int | None = None) -> proto.CommandReply:
        """ResetFault acknowledging `estop_seq` (default: the latest e-stop a status published
        after this call shows; once more with the next status if an e-stop engaged between
        that status and the reset)."""
        if estop_seq is not None:
            return self.command(proto.ResetFault(estop_seq=estop_seq))
        reply = self.command(proto.ResetFault(estop_seq=self.fresh_status().estop_seq))
        if reply.field == "body.estop_seq":
            reply = self.command(proto.ResetFault(estop_seq=self.fresh_status().estop_seq))
        return reply

    def put_estop(self, payload: bytes = b"") -> None:
        self.session.put(proto.key_estop(self.rig), payload)

    def wait_ready(self, proc: ControllerProcess | None = None, timeout_s: float = 120.0) -> None:
        """Until the controller answers a config GET (its queryable is up). The deadline is
        generous: start-up (the first gate run) takes 30-60 s at load 15 on 2 cores, and a
        controller that exits is reported at once."""
        deadline = time.monotonic() + timeout_s
        last = ""
        while time.monotonic() < deadline:
            if proc is not None and proc.proc.poll() is not None:
                raise ClientError(f"controller exited with {proc.proc.returncode}:\n{proc.log()}")
            try:
                self.query_raw(proto.key_config(self.rig), None, timeout_s=0.5)
                return
            except ClientError as exc:
                last = str(exc)
        log = proc.log() if proc is not None else ""
        raise ClientError(f"controller not ready within {timeout_s} s ({last})\n{log}")


def run_ctl(proc: ControllerProcess, *action: str, timeout_s: float = 30.0) -> tuple[int, str]:
    """`dobtune ctl <action>` against `proc`, in this process: (exit code, what it printed)."""
    import io

    from controller.cli.commands import controller_commands
    from controller.cli.common import build_parser
    from controller.cli.ctl import ctl_main

    args = build_parser("dobtune", None, controller_commands()).parse_args(
        ["ctl", "--connect", proc.endpoint, "--rig-name", proc.rig, "--timeout-s",
         str(timeout_s), *action])
    out = io.StringIO()
    return ctl_main(args, out), out.getvalue()


@contextlib.contextmanager
def watching(proc: ControllerProcess, log_path: Path,
             *extra: str) -> Iterator[subprocess.Popen[bytes]]:
    """`dobtune watch` beside `proc` (the article rig), its output in `log_path`; stopped
    (SIGTERM, then waited for) when the block ends."""
    with open(log_path, "ab") as log:
        watch = subprocess.Popen(
            [str(Path(sys.executable).parent / "dobtune"), "watch", "--connect", proc.endpoint,
             "--rig-name", proc.rig, "--disturbance", "article-rig",
             "--parent-pid", str(os.getpid()), *extra],
            stdout=log, stderr=subprocess.STDOUT)
        try:
            yield watch
        finally:
            watch.terminate()
            watch.wait(30)

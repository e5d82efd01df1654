"""Start-up: how long until a new controller is ready (listening, plant knowledge, config,
status), and how long `dobtune check` takes; this tree against an older commit, in one run.

    .venv/bin/python tests/bench/bench_startup.py --before main~3 [--runs 3] [--busy 8]

The older commit is exported (`git archive`) to a temporary directory and run from there with
the same interpreter. Each run starts a controller on a fresh state directory (the first start
of a rig: the plant knowledge and config v1 are saved) and measures, from the spawn: the port
accepting connections, the first status, the plant knowledge and the config answering. A
first, unmeasured start of each tree fills numba's cache. `--busy N` runs N busy loops beside
the measurement (the issue's "at load 10" on 2 cores: about 8). The machine's load average is
printed before and after. On a shared machine the wall times follow the others' load: the CPU
seconds are printed too (the controller process's own user+sys at ready, without its analysis
worker; `dobtune check`'s whole process).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import resource
import socket
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests"))

from helpers import free_port  # noqa: E402

from controller import protocol as proto  # noqa: E402
from controller.client import ClientOptions, ControllerClient, ControllerUnavailable  # noqa: E402


def export_tree(rev: str, into: Path) -> Path:
    """`rev` of this repository as files under `into` (no .git)."""
    out = into / rev.replace("/", "_").replace("~", "-")
    out.mkdir()
    archive = subprocess.run(["git", "-C", str(REPO), "archive", rev], check=True,
                             capture_output=True).stdout
    tar = into / "tree.tar"
    tar.write_bytes(archive)
    with tarfile.open(tar) as t:
        t.extractall(out, filter="data")
    return out


def _listening(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.2)
        return s.connect_ex(("127.0.0.1", port)) == 0


def _cpu_s(pid: int) -> float:
    """user + sys seconds of process `pid` so far (/proc/PID/stat)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def start_once(tree: Path, state: Path, timeout_s: float = 300.0) -> dict[str, float]:
    """Seconds from the spawn to: listening, status, knowledge, config (and `ready`: all);
    `ready CPU`: the controller process's CPU seconds when it was ready."""
    port = free_port()
    env = {**os.environ, "PYTHONPATH": str(tree)}
    cmd = [sys.executable, "-m", "controller", "--listen", f"tcp/127.0.0.1:{port}",
           "--rig-name", "bench", "--state-dir", str(state), "--log-level", "warning"]
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, cwd=tree, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    got: dict[str, float] = {}
    try:
        while not _listening(port):
            if proc.poll() is not None or time.monotonic() - t0 > timeout_s:
                raise RuntimeError(f"controller from {tree} did not listen (exit {proc.poll()})")
            time.sleep(0.005)
        got["listening"] = time.monotonic() - t0
        opts = ClientOptions(connect=(f"tcp/127.0.0.1:{port}",), rig_name="bench",
                             query_timeout_s=1.0)
        with ControllerClient(opts) as c:
            while len(got) < 4 and time.monotonic() - t0 < timeout_s:
                if "status" not in got and c.status is not None:
                    got["status"] = time.monotonic() - t0
                for what, ask in (("knowledge", c.knowledge), ("config", c.get_config)):
                    if what not in got:
                        with contextlib.suppress(ControllerUnavailable, proto.ProtocolError):
                            ask()
                            got[what] = time.monotonic() - t0
                time.sleep(0.005)
        got["ready"] = max(got.values())
        got["ready CPU"] = _cpu_s(proc.pid)
        return got
    finally:
        proc.send_signal(2)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def check_once(tree: Path) -> tuple[float, float]:
    """`dobtune check`'s wall and CPU (user + sys) seconds."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    code = ("import sys; from controller.cli.main import dobtune_main; "
            "sys.exit(dobtune_main(['check']))")
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-c", code], cwd=tree, env=env, capture_output=True)
    dt = time.monotonic() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if r.returncode not in (0, 3):
        raise RuntimeError(f"dobtune check from {tree}: exit {r.returncode}: {r.stderr[-500:]!r}")
    return dt, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


@contextlib.contextmanager
def busy_loops(n: int) -> Iterator[None]:
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    try:
        yield
    finally:
        for p in procs:
            p.kill()
            p.wait()


def _load() -> str:
    return "load average " + " ".join(f"{x:.2f}" for x in os.getloadavg())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--before", default="main", help="the commit to compare with (git rev)")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--busy", type=int, default=0, help="busy loops beside the measurement")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-startup-") as d:
        trees = {f"before ({a.before})": export_tree(a.before, Path(d)), "after (this tree)": REPO}
        for tree in trees.values():  # fill numba's cache, load the files once
            start_once(tree, Path(tempfile.mkdtemp(dir=d)))
            check_once(tree)
        print(f"{_load()} (before the measurement); {os.cpu_count()} CPUs; "
              f"{a.busy} busy loops beside it")
        rows: dict[str, dict[str, list[float]]] = {n: {} for n in trees}
        with busy_loops(a.busy):
            for _ in range(a.runs):  # interleaved: both trees see the same load
                for name, tree in trees.items():
                    for k, v in start_once(tree, Path(tempfile.mkdtemp(dir=d))).items():
                        rows[name].setdefault(k, []).append(v)
                    wall_s, cpu_s = check_once(tree)
                    rows[name].setdefault("dobtune check", []).append(wall_s)
                    rows[name].setdefault("check CPU", []).append(cpu_s)
            print(f"{_load()} (at the end of the measurement)")
        keys = ("listening", "status", "knowledge", "config", "ready", "ready CPU",
                "dobtune check", "check CPU")
        print(f"median of {a.runs} runs, seconds from the spawn (max in brackets):")
        print(f"  {'':22s}" + "".join(f"{k:>18s}" for k in keys))
        for name, r in rows.items():
            print(f"  {name:22s}" + "".join(
                f"{statistics.median(r[k]):10.2f} ({max(r[k]):5.2f})" for k in keys))


if __name__ == "__main__":
    main()

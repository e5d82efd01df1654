"""Benchmark: the audit log under a flood of e-stop puts (issue 31 item 2).

    .venv/bin/python tests/bench/bench_estop_flood_audit.py [--seconds 10] [--tree DIR]

One controller on the simulated rig (no authentication: loopback; every put is `local`'s). A
client of its own (another process's session, Zenoh's defaults) puts on the e-stop key as
fast as it can for `--seconds`; then an operator resets the latch (a real action, audited).
Printed: puts sent, audit records and bytes the flood added, the time from the end of the
flood until the accepted reset's record is in the log (the reset is sent again while e-stops
that arrived after it keep the latch) (the backlog in front of real actions), and
`dobtune audit verify` on the log.

`--tree DIR` runs the controller of another source tree (e.g. `git archive <commit> | tar -x
-C DIR`: the code before the e-stop records were counted).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: helpers
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "integration"))  # procs

from procs import REPO, Client, start_controller, wait_until

from controller import protocol as proto

_FLOOD = """
import json, sys, time, zenoh
conf = zenoh.Config()
conf.insert_json5("mode", '"peer"')
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("connect/endpoints", json.dumps([sys.argv[1]]))
key, seconds = sys.argv[2], float(sys.argv[3])
payload = sys.argv[4].encode("latin-1")
n = 0
with zenoh.open(conf) as s:
    pub = s.declare_publisher(key)
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        pub.put(payload)
        n += 1
print(n)
"""


def _records(path: Path) -> list[dict[str, object]]:
    return [json.loads(x) for x in path.read_bytes().splitlines() if x.strip()]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--tree", type=Path, default=None)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        proc = start_controller(Path(tmp) / "state", rig="eflood", tree=args.tree)
        log = proc.state_dir / "audit.jsonl"
        try:
            with Client(proc.endpoint, proc.rig) as client:
                client.wait_ready(proc)
                n0, b0 = len(_records(log)), log.stat().st_size
                body = proto.encode(proto.Command(body=proto.EStop(), client="flood"))
                out = subprocess.run(
                    [sys.executable, "-c", _FLOOD, proc.endpoint, proto.key_estop(proc.rig),
                     str(args.seconds), body.decode("latin-1")],
                    capture_output=True, text=True, check=True, cwd=REPO)
                puts = int(out.stdout.split()[-1])
                t_end = time.monotonic()
                replies: list[proto.CommandReply] = []

                def reset() -> bool:  # again while e-stops queued behind the flood arrive
                    replies.append(client.reset())
                    return replies[-1].ok

                wait_until(reset, 120.0, poll_s=0.2)
                reply = replies[-1]
                reset_written = wait_until(
                    lambda: any(r["action"] == "reset" and r["outcome"] == "accepted"
                                for r in _records(log)), 600.0)
                behind_s = time.monotonic() - t_end
                recs = _records(log)[n0:]
                added_bytes = log.stat().st_size - b0
        finally:
            proc.stop()
        verify = subprocess.run(
            [sys.executable, "-c", "import sys; from controller.cli.main import dobtune_main; "
             "sys.exit(dobtune_main())", "audit", "verify", str(proc.state_dir)],
            capture_output=True, text=True, cwd=REPO)
    estops = sum(1 for r in recs if r["action"] == "estop")
    counted = sum(int(r.get("count", 0)) for r in recs  # type: ignore[call-overload]
                  if r["action"] == "estop.repeated")
    print(f"controller tree: {args.tree or 'this one'}; {args.seconds:g} s of e-stop puts")
    print(f"puts sent: {puts} ({puts / args.seconds:.0f}/s); reset after the flood: "
          f"{'accepted' if reply.ok else 'refused: ' + reply.message}")
    print(f"audit: {len(recs)} records, {added_bytes / 1e6:.2f} MB added; e-stop records "
          f"{estops}, e-stops counted in estop.repeated records {counted}")
    print(f"resets sent: {len(replies)}; the accepted reset's record written {behind_s:.1f} s "
          f"after the flood ended "
          f"({'yes' if reset_written else 'NOT within 600 s'})")
    print(f"audit verify: exit {verify.returncode}: {verify.stdout.strip().splitlines()[0]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

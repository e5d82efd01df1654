"""Benchmark: the cross-session reset / e-stop race (issue 24) over many trials at given
offsets, against a real controller (simulated rig, real Zenoh on loopback). Prints figures;
not a test (`tests/integration/test_estop.py` runs a few trials and asserts).

    PYTHONPATH=$PWD .venv/bin/python tests/bench/bench_reset_race.py [--n 1000]
        [--offsets-ms 0,2,10] [--legacy]

Each trial (see `tests/integration/reset_race.py`): the operator e-stops and sends a reset
acknowledging that e-stop; `offset` later another session puts an e-stop; the rig must end in
e-stop. `--legacy` sends resets without `estop_seq` (run it with PYTHONPATH at a tree before
the fix to measure the hole).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: helpers, for procs
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "integration"))

from procs import Client, start_controller
from reset_race import run_trials

from controller.client.session import SessionOptions, connect


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1000)
    ap.add_argument("--offsets-ms", default="0,2,10")
    ap.add_argument("--legacy", action="store_true")
    args = ap.parse_args()
    offsets = [float(x) for x in args.offsets_ms.split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        proc = start_controller(Path(tmp) / "state", rig="bench-race",
                                extra_args=("--realtime-priority",))
        try:
            with Client(proc.endpoint, proc.rig) as probe:
                probe.wait_ready(proc, timeout_s=180.0)
            where = SessionOptions(connect=(proc.endpoint,))
            with connect(where) as a, connect(where) as b:
                print(f"{'offset':>8} {'trials':>7} {'held':>6} {'not stopped':>12} "
                      f"{'reset served':>13} {'reset refused':>14} {'s':>6}")
                for off in offsets:
                    t0 = time.monotonic()
                    r = run_trials(a, b, proc.rig, args.n, off / 1000.0, legacy=args.legacy)
                    print(f"{off:>6g}ms {r.trials:>7} {r.held:>6} {r.not_stopped:>12} "
                          f"{r.reset_ok:>13} {r.reset_refused:>14} "
                          f"{time.monotonic() - t0:>6.1f}", flush=True)
        finally:
            proc.stop()


if __name__ == "__main__":
    main()

"""Recordings complete under load (issue 33 item 4): samples expected, received live, recovered
from the controller's replay, and missing (with why), for a recording of --seconds with two
busy loops beside it (`python -c 'while 1: pass'` x2, killed after).

    nice -n 5 .venv/bin/python tests/bench/bench_record_complete.py --seconds 600

A simulated controller process (as `dobtune demo` starts it) is recorded by two recorder
processes at once, each the `Recorder` that `dobtune record` and the dashboard's Record run:
"before" without recovery (`recover=False`: what a recording was before the replay), "after"
with it. Both see the same stream on the same loaded machine. Expected = every seq from the
first sample recorded to the last; the loop's own drops (Status.timing.dropped_samples: the
ring to the publisher full) are printed beside: those were never published and are named
`never_published` when the replay still holds their neighbours.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: helpers, for procs
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "integration"))

from controller.recording.mcap_io import read_recording

_RECORD = """
import json, sys
from pathlib import Path
from controller.client.recorder import Recorder, RecordOptions
endpoint, rig, out, seconds, recover = sys.argv[1:6]
r = Recorder(RecordOptions(connect=(endpoint,), out=Path(out), rig_name=rig,
                           duration_s=float(seconds), timeout_s=120.0,
                           recover=recover == "1")).run()
print(json.dumps({"samples": r.samples, "lost": r.lost, "recovered": r.recovered,
                  "missing": r.missing, "summary": r.summary()}))
"""


def _load() -> str:
    return "load " + " ".join(f"{x:.1f}" for x in os.getloadavg())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="recording length (600: 10 min)")
    ap.add_argument("--busy", type=int, default=2, help="busy loops beside (default 2)")
    a = ap.parse_args()
    from procs import Client, free_port, start_controller

    with tempfile.TemporaryDirectory() as d:
        proc = start_controller(Path(d) / "state", port=free_port())
        busy: list[subprocess.Popen[bytes]] = []
        try:
            with Client(proc.endpoint, proc.rig) as c:
                c.wait_ready(proc, timeout_s=180.0)
                busy = [subprocess.Popen([sys.executable, "-c", "while 1: pass"])
                        for _ in range(a.busy)]
                print(f"{a.busy} busy loops started; {_load()}", flush=True)
                st0 = c.fresh_status()
                recs = {}
                for name, flag in (("before (no recovery)", "0"), ("after (replay)", "1")):
                    out = Path(d) / f"{flag}.mcap"
                    recs[name] = (out, subprocess.Popen(
                        [sys.executable, "-c", _RECORD, proc.endpoint, proc.rig, str(out),
                         str(a.seconds), flag], stdout=subprocess.PIPE, text=True))
                said = {n: json.loads(p.communicate(timeout=a.seconds + 300)[0])
                        for n, (_, p) in recs.items()}
                st1 = c.fresh_status()
                load_end = _load()
        finally:
            for b in busy:
                b.kill()
                b.wait()
            proc.stop()
        dropped = st1.timing.dropped_samples - st0.timing.dropped_samples
        print(f"recording {a.seconds:g} s with {a.busy} busy loops beside; at the end {load_end}")
        print(f"  the loop dropped {dropped} samples meanwhile (ring to the publisher full: "
              "never published)")
        for name, (out, _) in recs.items():
            r = said[name]
            rec = read_recording(out)
            seq = rec.state["seq"]
            expected = int(seq[-1] - seq[0] + 1) if seq.size else 0
            reasons = Counter()
            for lo, hi, why in r["missing"]:
                reasons[why] += hi - lo + 1
            print(f"  {name}: expected {expected}, received live "
                  f"{r['samples'] - r['recovered']}, recovered {r['recovered']}, missing "
                  f"{expected - int(seq.size)} ({dict(reasons) or 'none'}); in the file "
                  f"{seq.size} samples, {len(r['missing'])} gap ranges")
            print(f"    recorder said: {r['summary']}")


if __name__ == "__main__":
    main()

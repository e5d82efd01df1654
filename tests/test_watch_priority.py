"""The watch's `--priority idle` (issue 34): every thread of the process runs SCHED_IDLE, those
running before the call and those started after it (Zenoh's start with the session, later)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(not hasattr(os, "SCHED_IDLE") or not Path("/proc/self/task")
                                .is_dir(), reason="SCHED_IDLE and /proc: Linux only")

CODE = """
import os, threading
from controller.process.worker_start import idle_priority
go = threading.Event()
before = threading.Thread(target=go.wait)
before.start()
print(idle_priority())
after = threading.Thread(target=go.wait)
after.start()
print(sorted(os.sched_getscheduler(int(t)) for t in os.listdir('/proc/self/task')))
go.set()
before.join()
after.join()
"""


def test_idle_priority_covers_every_thread_also_later_ones() -> None:
    out = subprocess.run([sys.executable, "-c", CODE], cwd=REPO, capture_output=True,
                         text=True, timeout=120, check=True).stdout.splitlines()
    assert out[0] == "SCHED_IDLE (2 threads)"
    assert out[1] == str([os.SCHED_IDLE] * 3)


"""A twin fit held until the test lets it go (tests/integration/test_twin_no_wait.py).

The controller's code is the product's; only the fit's entry point is wrapped (the controller
started with `python_code` sets `controller.process.service.build_twin` to `build_twin_held`).
Runs in the worker process that fits the twin: it appends the record's version to the file
`<hold>.started` when a fit begins, waits until the file `<hold>` exists (the test's release),
then fits for real. A hold never released ends after HOLD_MAX_S (the test failed meanwhile).
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

from controller.twin.fit import build_twin

#: The environment variable naming the hold file (inherited by the worker processes).
HOLD_ENV = "DOBTUNE_TEST_TWIN_HOLD"
HOLD_MAX_S = 900.0


def build_twin_held(rec: Any, *args: Any) -> Any:
    hold = Path(os.environ[HOLD_ENV])
    with open(f"{hold}.started", "a") as f:
        f.write(f"{rec.version}\n")
    deadline = time.monotonic() + HOLD_MAX_S
    while not hold.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    return build_twin(rec, *args)


def controller_code(hold: Path) -> str:
    """`python -c` code: the controller (`python -m controller`, its arguments in argv) with
    every twin fit held on `hold`."""
    here = str(Path(__file__).resolve().parent)
    return (
        "import os, sys\n"
        f"sys.path.insert(0, {here!r})\n"
        f"os.environ[{HOLD_ENV!r}] = {str(hold)!r}\n"
        "import twin_hold\n"
        "import controller.process.service as service\n"
        "service.build_twin = twin_hold.build_twin_held\n"
        "from controller.__main__ import main\n"
        "sys.exit(main(sys.argv[1:]))\n"
    )

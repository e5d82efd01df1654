"""Fixtures that start real controller processes on free loopback ports.

- `start_controller(state_dir=None, **kw)`: a factory; every process it starts is stopped
  (SIGINT) at teardown, and its port is checked to be free again.
- `controller`: one ready controller (simulated plant) with its own state directory.
- `module_controller`: the same, one for a whole module (a module takes it as its
  `controller`): for modules whose tests leave the controller as they found it (running, on
  its trajectory, not e-stopped; restored in `finally`) and read only changes they made
  themselves. A start-up is seconds of the suite's time (interpreter, imports, compiled plant).
- `client`: the test's own Zenoh peer connected to `controller`.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from procs import Client, ControllerProcess, port_is_free, start_controller, wait_until


@contextlib.contextmanager
def _controllers(base: Path) -> Iterator[Callable[..., ControllerProcess]]:
    """A factory of controllers with state directories under `base`; every one started is
    stopped on exit and its port checked to be free again."""
    started: list[ControllerProcess] = []
    counter = iter(range(1000))

    def start(state_dir: Path | None = None, **kw: Any) -> ControllerProcess:
        sd = state_dir if state_dir is not None else base / f"state{next(counter)}"
        proc = start_controller(sd, **kw)
        started.append(proc)
        return proc

    yield start
    for p in started:
        p.stop()
    for p in started:
        assert wait_until(functools.partial(port_is_free, p.port), 5.0), (
            f"port {p.port} still in use"
        )


@pytest.fixture
def start_controller_factory(tmp_path: Path) -> Iterator[Callable[..., ControllerProcess]]:
    with _controllers(tmp_path) as start:
        yield start


#: A controller as it runs on a rig: --realtime-priority (SCHED_FIFO for the loop thread).
#: At normal priority on this shared 2-core machine the kernel's late wake-ups skip 5-9 % of
#: the ticks under load (measured with the code before and after the layout change), which
#: the rate and flood tests would report as the controller's fault.
RIG_ARGS = ("--realtime-priority",)


@pytest.fixture
def controller(start_controller_factory: Callable[..., ControllerProcess]) -> ControllerProcess:
    """A controller of the test's own (`RIG_ARGS`)."""
    return start_controller_factory(extra_args=RIG_ARGS)


@pytest.fixture(scope="module")
def module_controller(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ControllerProcess]:
    """One controller (`RIG_ARGS`) for a module's tests (see the module docstring)."""
    with _controllers(tmp_path_factory.mktemp("controller")) as start:
        yield start(extra_args=RIG_ARGS)


@pytest.fixture
def client(controller: ControllerProcess) -> Iterator[Client]:
    with Client(controller.endpoint, controller.rig) as c:
        c.wait_ready(controller)
        yield c

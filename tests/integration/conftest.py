"""Fixtures that start real controller processes on free loopback ports.

- `start_controller(state_dir=None, **kw)`: a factory; every process it starts is stopped
  (SIGINT) at teardown, and its port is checked to be free again.
- `controller`: one ready controller (simulated plant) with its own state directory.
- `client`: the test's own Zenoh peer connected to `controller`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from procs import Client, ControllerProcess, port_is_free, start_controller, wait_until


@pytest.fixture
def start_controller_factory(tmp_path: Path) -> Iterator[Callable[..., ControllerProcess]]:
    started: list[ControllerProcess] = []
    counter = iter(range(1000))

    def start(state_dir: Path | None = None, **kw: Any) -> ControllerProcess:
        sd = state_dir if state_dir is not None else tmp_path / f"state{next(counter)}"
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
def controller(start_controller_factory: Callable[..., ControllerProcess]) -> ControllerProcess:
    """A controller as it runs on a rig: --realtime-priority (SCHED_FIFO for the loop thread).
    At normal priority on this shared 2-core machine the kernel's late wake-ups skip 5-9 % of
    the ticks under load (measured with the code before and after the layout change), which
    the rate and flood tests would report as the controller's fault."""
    return start_controller_factory(extra_args=("--realtime-priority",))


@pytest.fixture
def client(controller: ControllerProcess) -> Iterator[Client]:
    with Client(controller.endpoint, controller.rig) as c:
        c.wait_ready(controller)
        yield c

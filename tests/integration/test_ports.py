"""A busy Zenoh port: the second controller says so and exits 2 (no traceback)."""

from __future__ import annotations

from collections.abc import Callable

from procs import Client, ControllerProcess


def test_a_second_controller_on_a_busy_port_exits_2_with_a_message(
    controller: ControllerProcess, client: Client,
    start_controller_factory: Callable[..., ControllerProcess],
) -> None:
    second = start_controller_factory(port=controller.port)
    assert second.proc.wait(timeout=60) == 2
    log = second.log()
    assert "--listen" in log and "port in use" in log
    assert "Traceback" not in log

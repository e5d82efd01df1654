"""The runtime's publisher is not woken by the tick for each full block (the wake-up cost the
handing-off tick ~35 us): it wakes on the loop's deadline grid, after the tick that completes a
block; a block cut short (new configuration) and the loop's end still wake it at once."""

from __future__ import annotations

import threading

from helpers import wait_until

from controller.core.config import LoopConfig
from controller.core.loop import LoopCoefficients, ServoLoop
from controller.process.requests import ApplyCoefficients
from controller.process.runtime import Runtime, RuntimeOptions
from controller.sim.sim_rig import SimRig


class NullRig:
    def read(self) -> tuple[float, float]:
        return 0.1, 0.2

    def step(self, command_deg_s: float) -> None:
        pass


def _loop(version: int = 1, **cfg: object) -> ServoLoop:
    return ServoLoop(LoopCoefficients.build(LoopConfig(**cfg), version))  # type: ignore[arg-type]


def test_a_full_block_does_not_wake_the_publisher_a_short_one_does() -> None:
    rt = Runtime(_loop(), NullRig(), options=RuntimeOptions(batch_size=20, ring_blocks=8))
    ring = rt._ring
    for k in range(45):
        rt._tick(k * 1e-3)
    assert ring.produced == 2  # two full blocks handed off
    assert not ring.ready.is_set()
    ticket = rt.submit(ApplyCoefficients(LoopCoefficients.build(LoopConfig(), 2)))
    rt._tick(45e-3)  # the new version cuts the block of 5 short: handed off with a wake
    assert ticket.done.is_set() and ticket.ok
    assert ring.produced == 3 and ring.n[2] == 5
    assert ring.ready.is_set()


def test_blocks_reach_the_publisher_while_the_loop_runs_without_a_wake_or_a_poll() -> None:
    rt = Runtime(_loop(), SimRig(), options=RuntimeOptions(batch_size=20))
    got: list[int] = []
    stop = threading.Event()
    # An hour's poll: only the wake on the deadline grid can bring blocks before the loop ends.
    pub = threading.Thread(target=rt.publisher,
                           args=(lambda seq0, *_: got.append(seq0), stop, 3600.0))
    loop = threading.Thread(target=rt.run)
    pub.start()
    loop.start()
    try:
        assert wait_until(lambda: len(got) >= 10, 120.0), got
        assert not rt.finished.is_set()
    finally:
        rt.stop()
        loop.join(30.0)
        stop.set()
        pub.join(30.0)
    assert not loop.is_alive() and not pub.is_alive()
    assert got == list(range(0, 20 * len(got), 20))  # in order, none lost, the last flushed

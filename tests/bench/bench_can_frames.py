"""Per-tick cost of the CAN frame path, in microseconds.

    .venv/bin/python tests/bench/bench_can_frames.py

1. pure: pack the RPDO1 command, parse TPDO1 + TPDO2 + the load encoder frame (cia402 only);
2. adapter: CanRig.step() + CanRig.read() against an in-memory python-can bus that answers
   each SYNC at once (python-can Message objects included, no threads, no kernel);
3. round trip: the same through python-can's virtual bus and the simulated drive node on its
   thread (dominated by the virtual bus's deepcopy and the thread hand-over, not by us).
"""

from __future__ import annotations

import collections
import dataclasses
import time
import uuid
from pathlib import Path
from typing import Any

import can

from controller.rig import cia402
from controller.rig.can_rig import CanRig
from controller.rig.rig_file import RigFile, load_rig_file
from controller.rig.sim_drive_node import SimDriveNode

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "rig_cia402.toml"


def bench_pure(n: int) -> float:
    tpdo1 = cia402.make_tpdo_status_velocity(0x0237, 2200)
    tpdo2 = cia402.make_tpdo_position(123456)
    encoder = (1 << 25).to_bytes(4, "little")
    codec = cia402.FieldCodec(0, 4, False, "little")
    make = cia402.make_rpdo_command
    parse1 = cia402.parse_tpdo_status_velocity
    parse2 = cia402.parse_tpdo_position
    decode = cia402.decode_state
    t0 = time.perf_counter()
    for k in range(n):
        make(0x000F, k & 0xFFFF)
        statusword, _ = parse1(tpdo1)
        decode(statusword)
        parse2(tpdo2)
        codec.decode(encoder)
    return (time.perf_counter() - t0) / n * 1e6


class LoopbackBus(can.BusABC):
    """Answers every SYNC with the drive's three feedback frames, in the caller's thread."""

    def __init__(self, channel: Any = None, **kwargs: Any) -> None:
        super().__init__(channel=channel, **kwargs)
        self.queue: collections.deque[can.Message] = collections.deque()
        self.counts = 0

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if msg.arbitration_id == 0x080:
            self.counts += 1000
            for can_id, data in (
                (0x181, cia402.make_tpdo_status_velocity(0x0237, 2200)),
                (0x281, cia402.make_tpdo_position(self.counts // 10)),
                (0x190, (self.counts % (1 << 26)).to_bytes(4, "little")),
            ):
                self.queue.append(
                    can.Message(arbitration_id=can_id, data=data, is_extended_id=False)
                )

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return (self.queue.popleft() if self.queue else None), False


def _ready(rig: CanRig) -> None:
    """Arm the adapter without the SDO/NMT bring-up (the loopback has no SDO server)."""
    rig.step(0.0)
    rig.read()
    rig._enabled = True  # bench only: skip start()
    rig._stopped = False


def _us_per_tick(rig: CanRig, n: int) -> float:
    """Microseconds per tick (read, then step at 10 deg/s) over `n` ticks; the rig ends without
    a fault."""
    t0 = time.perf_counter()
    for _ in range(n):
        rig.read()
        rig.step(10.0)
    elapsed = time.perf_counter() - t0
    assert rig.fault is None, rig.fault
    return elapsed / n * 1e6


def bench_adapter(n: int, rig_file: RigFile) -> float:
    # no heartbeat supervision: the loopback has no heartbeat producer
    rig_file = dataclasses.replace(
        rig_file, drive=dataclasses.replace(rig_file.drive, heartbeat_period_ms=0)
    )
    bus = LoopbackBus()
    with CanRig(rig_file, bus=bus, wait_feedback_s=0.0) as rig:
        _ready(rig)
        us = _us_per_tick(rig, n)
    bus.shutdown()
    return us


def bench_round_trip(n: int, rig_file: RigFile) -> float:
    rig_file = dataclasses.replace(
        rig_file,
        bus=dataclasses.replace(
            rig_file.bus, interface="virtual", channel=f"bench-{uuid.uuid4().hex}"
        ),
    )
    with SimDriveNode(rig_file) as _node, CanRig(rig_file, wait_feedback_s=0.1) as rig:
        rig.start()
        return _us_per_tick(rig, n)


def main() -> None:
    rig_file = load_rig_file(EXAMPLE)
    bench_pure(2000)
    print(f"pure pack+parse per tick:           {bench_pure(200_000):7.2f} us")
    print(f"CanRig read+step, in-memory bus:    {bench_adapter(20_000, rig_file):7.2f} us")
    print(f"round trip, virtual bus + sim node: {bench_round_trip(2000, rig_file):7.2f} us")


if __name__ == "__main__":
    main()

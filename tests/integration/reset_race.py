"""The cross-session reset / e-stop race (issue 24), shared by the integration test and
`tests/bench/bench_reset_race.py`.

One trial, against a real controller over real Zenoh, two sessions:
1. the operator (session A) e-stops with the EStop command and notes the e-stop seq its reply
   names (what its Status would show);
2. A sends a reset acknowledging that e-stop (its reply is not awaited);
3. `offset_s` later a second session B (another user, another dashboard) puts an e-stop on the
   e-stop key, then sends a Stop: it changes nothing and, queued behind B's e-stop on the same
   link, proves that e-stop reached the controller;
4. once both replies are in, A's Stop asks the mode: the rig must still be in e-stop, whatever
   order the reset and the e-stop arrived in.
`legacy=True` sends the reset without `estop_seq`, as before issue 24 (against the code
before the fix, with PYTHONPATH at that tree, it measures the hole).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from controller import protocol as proto


@dataclass
class RaceResult:
    trials: int = 0
    held: int = 0  # the rig ended in e-stop
    reset_ok: int = 0  # the reset was served (it came before the e-stop) ...
    reset_refused: int = 0  # ... or refused (a newer e-stop, or one that arrived after it)

    @property
    def not_stopped(self) -> int:
        return self.trials - self.held


def _command(body: Any) -> bytes:
    return proto.encode(proto.Command(body=body, client="reset-race"))


def _reply(replies: Iterator[Any], what: str) -> proto.CommandReply:
    for r in replies:
        if r.ok is not None:
            return proto.decode(r.ok.payload.to_bytes(), proto.CommandReply)
        raise AssertionError(f"{what}: error reply {r.err.payload.to_string()}")
    raise AssertionError(f"{what}: no reply")


def _wait(offset_s: float) -> None:
    if offset_s <= 0.0:
        return
    until = time.perf_counter() + offset_s
    if offset_s > 0.003:
        time.sleep(offset_s - 0.002)
    while time.perf_counter() < until:
        pass


def run_trials(
    operator: Any, other: Any, rig: str, n: int, offset_s: float, *, legacy: bool = False
) -> RaceResult:
    """`n` trials; `operator` and `other` are two open Zenoh sessions to the controller."""
    cmd_key, estop_key = proto.key_command(rig), proto.key_estop(rig)
    estop, stop = _command(proto.EStop()), _command(proto.Stop())
    res = RaceResult()
    for i in range(n):
        seen = _reply(operator.get(cmd_key, payload=estop, timeout=10.0), f"trial {i} e-stop")
        assert seen.ok and seen.mode == "estop", seen
        body = proto.ResetFault() if legacy else proto.ResetFault(estop_seq=seen.seq)
        pending = operator.get(cmd_key, payload=_command(body), timeout=10.0)
        _wait(offset_s)
        other.put(estop_key, b"")
        _reply(other.get(cmd_key, payload=stop, timeout=10.0), f"trial {i} barrier")
        reset = _reply(pending, f"trial {i} reset")
        probe = _reply(operator.get(cmd_key, payload=stop, timeout=10.0), f"trial {i} probe")
        res.trials += 1
        res.held += probe.mode == "estop"
        res.reset_ok += reset.ok
        res.reset_refused += not reset.ok
    return res

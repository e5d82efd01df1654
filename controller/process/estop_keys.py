"""What the edge process and the loop process's node share about e-stops (one module both
import: the edge relays e-stops to the tick, the node keeps the fallback and the audit): the
flag array's slots, the public sender's name, and what an e-stop sample claims about its
sender."""

from __future__ import annotations

from typing import Any

from controller import protocol as proto

__all__ = ["ACTIVE_VERSION", "ESTOP_ARRIVAL", "ESTOP_FLAG", "PUBLIC", "SLOTS", "estop_claims"]

#: The e-stop flag array's slots: 1 while an e-stop waits for the tick; the newest e-stop's
#: arrival stamp (`time.monotonic_ns`, the clock the loop stamps requests with).
ESTOP_FLAG = 0
ESTOP_ARRIVAL = 1
#: The third slot: the version of the configuration the loop runs (written by the loop when
#: it starts a sample block, so before any status or stream shows it): the edge serves its
#: snapshot of the configuration only when it is of that version (a watchdog rollback's
#: snapshot can reach it after the status that shows the rollback).
ACTIVE_VERSION = 2
SLOTS = 3

#: The sender of an e-stop on the public key under authentication: any authenticated user may
#: put there and Zenoh does not say who did (a user's own scope names the user).
PUBLIC = "public"
#: Largest e-stop payload whose claims are read for the audit (the e-stop itself ignores it).
_CLAIMS_MAX_BYTES = 4096


def estop_claims(sample: Any) -> dict[str, str]:
    """What an e-stop sample claims about its sender, for the audit (claims, not identity):
    the client name of its Command and the Zenoh session id the sender set (source_info)."""
    out: dict[str, str] = {}
    data = sample.payload.to_bytes()
    if len(data) <= _CLAIMS_MAX_BYTES:
        try:
            out["claimed_client"] = proto.decode(data, proto.Command).client
        except proto.ProtocolError:
            out["claimed_client"] = f"(not a Command: {len(data)} bytes)"
    info = sample.source_info
    if info is not None and info.source_id is not None:
        out["claimed_session"] = str(info.source_id)
    return out

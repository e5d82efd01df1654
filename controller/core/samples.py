"""The loop's per-tick sample: what the runtime stores every tick and the state stream carries.

Defined here, in the pure core, so the runtime and the wire contract (`controller.protocol`,
whose StateBatch has one list field per column) share the names without depending on each
other.
"""

from __future__ import annotations

from controller.core.arrays import FloatArray

__all__ = ["STATE_COLUMNS", "TickSamples"]

#: The per-sample columns, in order (angles in load-side degrees, speeds in load-side deg/s).
STATE_COLUMNS: tuple[str, ...] = (
    "t_s",
    "ref_deg",
    "pos_deg",
    "speed_deg_s",
    "speed_ref_deg_s",
    "command_deg_s",
    "d_hat_deg_s",
    "error_deg",
)


class TickSamples:
    """A window of these samples, one per tick (`command_deg_s`, at `rate_hz`): its length
    and duration. The base of the watch's `Window` and the twin's `RunningWindow`."""

    rate_hz: float
    command_deg_s: FloatArray

    @property
    def n(self) -> int:
        return int(self.command_deg_s.size)

    @property
    def duration_s(self) -> float:
        return self.n / self.rate_hz

"""The controller process's options (built by `controller.cli.controller` from the command line)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from controller.client.session import DEFAULT_LISTEN
from controller.core.trajectory import Trajectory

__all__ = ["ControllerOptions"]


@dataclass(frozen=True)
class ControllerOptions:
    """Everything `run_controller` needs."""

    plant: str = "sim"
    """"sim" (the simulated rig, in lockstep with the loop) or "can" (needs rig_file)."""
    rig_file: Path | None = None
    rig_name: str = "demo"
    """The `<rig>` chunk of every key."""
    listen: tuple[str, ...] = DEFAULT_LISTEN
    connect: tuple[str, ...] = ()
    config_path: Path | None = None
    """An initial LoopConfig (JSON). It goes through the gate like any candidate."""
    state_dir: Path | None = None
    """Active config + applied-changes log; default ./var/<rig_name>."""
    rate_hz: float | None = None
    """Loop rate override (otherwise the configuration's rate_hz)."""
    seed: int = 0
    realtime_priority: bool = False
    trajectory: Trajectory = field(default_factory=Trajectory)
    status_period_s: float = 0.2
    loop_summary_period_s: float = 60.0
    """How often lost ticks (overruns, skipped ticks, dropped samples) are logged, if any."""
    max_payload_bytes: int = 64 * 1024
    """Larger queries are rejected before decoding."""
    max_pending_queries: int = 256
    """Per queryable; beyond this, new queries are dropped unanswered."""
    apply_timeout_s: float = 1.0
    """How long a request waits for the loop's tick boundary before replying with an error."""
    command_timeout_s: float = 5.0
    """The same for commands: a reset re-enables the drive inside the loop (CAN: up to the
    rig file's enable_timeout_s)."""
    spin_s: float = 0.0002
    switch_interval_s: float = 0.0002
    """sys.setswitchinterval for this process: bounds how long another Python thread can
    keep the loop's thread waiting for the interpreter lock."""
    gate_in_subprocess: bool = True
    """Run the stability analysis in a worker process (see AnalysisWorker)."""
    edge_in_subprocess: bool = True
    """Serve the request queryables from the edge process (`controller.process.edge`), apart
    from the loop's process (False: from threads of this process, as before issue 31)."""
    request_budget_per_s: float = 50.0
    """With `auth_dir`: requests a second each user may send (bursts of twice that); beyond,
    a request is refused at once, naming the budget (`controller.process.budget`; the edge
    process only)."""
    auth_dir: Path | None = None
    """`dobtune auth init` directory: user/password authentication, access control per role,
    requests on per-user key scopes, the operator lease enforced for every user."""
    auth_user: str = ""
    """With `auth_dir` and `connect` (an authenticating router): the account, of role
    "controller", this controller logs in with; it then listens nowhere and is reached only
    through the router, which enforces the access control."""
    insecure: bool = False
    """Allow a non-loopback listen endpoint without `auth_dir` (anyone who reaches it can
    change the rig while nobody holds the lease)."""
    sim_disturbances: tuple[str, ...] = ()
    """plant="sim" only: named disturbances of the simulated rig
    (`controller.sim.rig_disturbances`: rig parameters and load-torque profiles; scheduled
    friction changes are for offline experiments), e.g. the demo's rate disturbances."""
    sim_drive_node: bool = False
    """plant="can" only: run a simulated CiA 402 drive node in this process on the rig
    file's bus (python-can `virtual`): the whole CAN path without hardware."""

    @property
    def state_path(self) -> Path:
        """The state directory in effect."""
        return self.state_dir if self.state_dir is not None else Path("var") / self.rig_name

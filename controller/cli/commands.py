"""The controller side's `dobtune` commands (light imports: each module imports its work
lazily, so listing them loads no analysis, no Zenoh and no dashboard)."""

from __future__ import annotations

from controller.cli import (
    audit,
    auth,
    autotune,
    check,
    controller,
    ctl,
    experiment,
    identify,
    paper,
    record,
    report,
    router,
)
from controller.cli.common import Command

__all__ = ["controller_commands"]


def controller_commands() -> dict[str, Command]:
    """Every controller-side command by name."""
    return {c.name: c for c in (experiment.COMMAND, check.COMMAND, controller.COMMAND,
                                identify.COMMAND, audit.COMMAND, auth.COMMAND, ctl.COMMAND,
                                record.COMMAND, report.COMMAND, router.COMMAND,
                                autotune.COMMAND, paper.COMMAND)}

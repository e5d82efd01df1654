"""`python -m server`: the dashboard (the same as `dobtune dashboard`).

The `dobtune` console script is `controller.cli.main.dobtune_main` (re-exported here for the
callers that started it as `server.__main__`)."""

from __future__ import annotations

import sys

from controller.cli import dashboard as dashboard_cmd
from controller.cli.common import IntermixedParser, add_log_level
from controller.cli.dashboard import candidates_dir
from controller.cli.main import dobtune_main

__all__ = ["candidates_dir", "dobtune_main", "main"]


def main(argv: list[str] | None = None) -> int:
    parser = IntermixedParser(prog="python -m server", description="dobtune dashboard")
    dashboard_cmd.add_arguments(parser)
    add_log_level(parser)
    return dashboard_cmd.run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())

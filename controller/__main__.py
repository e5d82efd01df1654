"""`python -m controller`: the controller process (the same as `dobtune controller`)."""

from __future__ import annotations

import sys

from controller.cli import controller as controller_cmd
from controller.cli.common import IntermixedParser, add_log_level


def main(argv: list[str] | None = None) -> int:
    parser = IntermixedParser(
        prog="python -m controller", description="dobtune controller process"
    )
    controller_cmd.add_arguments(parser)
    add_log_level(parser)
    return controller_cmd.run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())

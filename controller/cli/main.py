"""`dobtune` console script (all subcommands; also `python -m controller.cli.main`)."""

from __future__ import annotations

from controller.cli.commands import all_commands
from controller.cli.common import build_parser

__all__ = ["dobtune_main"]


def dobtune_main(argv: list[str] | None = None) -> int:
    """The `dobtune` command line: parse `argv` (default sys.argv[1:]), run the command."""
    cmds = all_commands()
    args = build_parser("dobtune", __doc__, cmds).parse_args(argv)
    return cmds[args.command].run(args)


if __name__ == "__main__":  # `python -m controller.cli.main <command>`
    import sys

    sys.exit(dobtune_main())

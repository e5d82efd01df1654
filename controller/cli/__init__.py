"""The `dobtune` subcommands, one module each (front ends over the library; no argv here).

Every command module exports `COMMAND` (`controller.cli.common.Command`): its help line, the
function that declares its options and the function that runs it. `commands.py` lists them;
parsing happens only in `controller/__main__.py` and `server/__main__.py`.
"""

"""The `dobtune` subcommands, one module each (front ends over the library; no argv here).

Every command module exports `add_arguments` (declares its options) and `run` (runs it);
`commands.py` lists them with their help lines (`controller.cli.common.lazy_command`: a
command's module is imported only when that command is used). The `dobtune` console script is
`main.py` (`dobtune_main`, also `python -m controller.cli.main`); parsing happens only there
and in `controller/__main__.py` (`python -m controller`). The dashboard's package imports
nothing of this one: `dobtune dashboard` and `demo` load it when they run.
"""

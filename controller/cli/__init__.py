"""The `dobtune` subcommands, one module each (front ends over the library; no argv here).

Every command module exports `add_arguments` (declares its options) and `run` (runs it);
`commands.py` lists them with their help lines (`controller.cli.common.lazy_command`: a
command's module is imported only when that command is used). Parsing happens only in
`controller/__main__.py` and `server/__main__.py`.
"""

"""The dashboard's composition: `app` (the `Dashboard`: builds the GUI, wires the parts, runs),
`candidates` (each browser's own candidate panels) and `demo` (a simulated controller and the
dashboard). It imports the panels (`server/panels/`) and the helpers (`server/*.py`); nothing
imports it but the commands that run it (`controller/cli/dashboard.py`, `demo.py`) and tests."""

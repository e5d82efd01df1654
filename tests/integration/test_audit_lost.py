"""Issue 31 item 5: an audit log deleted while the controller runs, or gone at its restart.

Before: the controller kept writing to the deleted file (its open descriptor) and nothing said
so; after a restart it started a new chain that `dobtune audit verify` called intact. Now the
deletion is a Status note within about a second, the log is reopened as a continuation that
says so, and a restart whose state directory had history (the head file) does not start a
new intact chain.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import pytest
from procs import Client, start_controller, wait_until

from controller.cli.audit import verify_main
from controller.process.audit import CONTINUED

pytestmark = pytest.mark.integration


def _first(path: Path) -> dict[str, object]:
    data = path.read_bytes() if path.exists() else b""
    return json.loads(data.splitlines()[0]) if data.strip() else {}


def _verify(state_dir: Path) -> tuple[int, str]:
    out = io.StringIO()
    return verify_main(state_dir, None, False, out), out.getvalue()


def test_a_deleted_log_is_noticed_while_running_and_not_restarted_silently(
    tmp_path: Path,
) -> None:
    state = tmp_path / "state"
    proc = start_controller(state, rig="auditlost")
    log = state / "audit.jsonl"
    try:
        with Client(proc.endpoint, proc.rig) as client:
            client.wait_ready(proc)
            assert _verify(state)[0] == 0
            log.unlink()
            # No request needed: the writer notices within its second, the status says so.
            assert wait_until(lambda: any("deleted while the controller ran" in n
                                          for n in client.fresh_status().notes), 20.0)
            assert _first(log).get("action") == CONTINUED
            client.get_config()
    finally:
        proc.stop()
    code, text = _verify(state)
    assert code == 1 and "audit.continued" in text

    # Deleted while stopped: the restart continues the chain and says so; verify is not fooled.
    log.unlink()
    proc = start_controller(state, rig="auditlost", port=proc.port)
    try:
        with Client(proc.endpoint, proc.rig) as client:
            client.wait_ready(proc)
            assert any("missing" in n for n in client.fresh_status().notes)
    finally:
        proc.stop()
    first = _first(log)
    assert first.get("action") == CONTINUED and first.get("lost_head")
    code, text = _verify(state)
    assert code == 1 and "not in this file" in text

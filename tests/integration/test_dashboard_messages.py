"""A viewer's raw websocket against a dashboard of a controller with authentication (issue 31
item 5): a controller with `--auth` (operator op1, viewer view), a dashboard given the auth
directory (one URL per user), and raw websocket clients speaking viser's protocol with each
user's token, as a hostile viewer would.

Measured before the message gate: one message from the viewer emptied the E-STOP button's
callbacks for every browser (`update_cb: []`), `removed: true` did the same to Reset fault,
and the shared controls took the viewer's values."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from helpers import answers, wait_for
from procs import free_port, start_controller, wait_until
from viser_raw import RawViser

from controller.auth import init_auth_dir, new_users
from controller.client import ClientOptions, ControllerClient
from server.dashboard.app import Dashboard, DashboardOptions
from server.viser_adapter import control_uuid

RIG = "msggate"


@pytest.fixture(scope="module")
def dash(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Dashboard]:
    base = tmp_path_factory.mktemp("msggate")
    auth = base / "auth"
    init_auth_dir(auth, new_users([("op1", "operator"), ("view", "viewer")]))
    proc = start_controller(base / "state", rig=RIG, extra_args=("--auth", str(auth)))
    try:
        probe_opts = ClientOptions(connect=(proc.endpoint,), rig_name=RIG, auth=auth,
                                   user="view", client_name="probe", connect_timeout_s=60.0)
        with ControllerClient(probe_opts) as probe:
            assert wait_until(lambda: answers(probe), 180.0, poll_s=0.5), proc.log()
        opts = DashboardOptions(connect=(proc.endpoint,), rig_name=RIG, port=free_port(),
                                verbose=False, auth=auth, recordings_dir=base / "rec",
                                candidates_dir=base / "cand")
        with Dashboard(opts) as d:
            yield d
    finally:
        proc.stop()


def _as(dash: Dashboard, user: str) -> RawViser:
    url = dash.url_for(user)
    c = RawViser(url.replace("http://", "ws://"), origin=url.split("/?")[0])
    assert dash.server is not None
    wait_for(lambda: user in {dash.sessions.user_of(b)
                              for b in dash.server.get_clients().values()}, 30.0,
             f"{user}'s browser was never signed in")
    return c


def _sync(dash: Dashboard, c: RawViser) -> None:
    """Wait until what `c` sent so far was judged: its E-STOP press (allowed for every
    role) reached the E-STOP's callbacks."""
    assert dash.live is not None
    pressed: list[int] = []
    handle = dash.live.estop_button
    handle.on_click(lambda e: pressed.append(e.client_id))
    c.update(control_uuid(handle), {"value": True})
    wait_for(lambda: pressed, 30.0, "the E-STOP press reached no callback")
    handle._impl.update_cb.pop()  # the test's own callback (viser has no off_click)


def test_a_viewer_changes_no_shared_control_and_breaks_none(dash: Dashboard) -> None:
    assert dash.live is not None and dash.messages is not None and dash.history is not None
    live = dash.live
    estop_callbacks = list(live.estop_button._impl.update_cb)
    window, trajectory = live.window_s.value, live.trajectory.value
    refused = dash.messages.refused
    with _as(dash, "view") as viewer:
        attacks: list[tuple[Any, dict[str, Any]]] = [
            (live.estop_button, {"update_cb": []}),
            (live.run_buttons, {"removed": True}),
            (live.window_s, {"value": 30.0}),          # a valid value, but everyone's
            (live.trajectory, {"value": "step"}),      # ditto
            (live.run_buttons, {"value": "Start"}),    # an operator's action
            (live.run_buttons, {"value": "Reset fault"}),
        ]
        for handle, updates in attacks:
            viewer.update(control_uuid(handle), updates)
        _sync(dash, viewer)
        assert dash.messages.refused == refused + len(attacks)
        # A refusal is told to that viewer: a notification in its own page.
        viewer.pump_until(lambda: any(
            m["type"] == "NotificationShowMessage" and "view is a viewer" in str(m)
            for m in viewer.messages), 30.0, "the viewer was not told")
    assert live.estop_button._impl.update_cb == estop_callbacks
    assert not live.run_buttons._impl.removed
    assert live.window_s.value == window and live.trajectory.value == trajectory
    # The operator still changes them.
    with _as(dash, "op1") as op:
        op.update(control_uuid(live.window_s), {"value": 31.0})
        wait_for(lambda: live.window_s.value == 31.0, 30.0, "the operator's change was lost")

"""A browser that closes while the dashboard builds its own panels (seen in a CI run: viser's
thread pool printed "Task failed with exception ... KeyError" from `_on_client_connect`, the
browser's containers having been removed by its departure). The departure is ordinary: the
dashboard says so at info, keeps nothing built for the departed browser (its disconnect
callback may have run first) and stays whole for the next browser."""

from __future__ import annotations

import logging
from collections.abc import Iterator

import pytest
from helpers import answers, wait_for
from procs import free_port, start_controller, wait_until
from viser_raw import connected

from controller.client import ClientOptions, ControllerClient
from server.dashboard.app import Dashboard, DashboardOptions

RIG = "leaves"


@pytest.fixture(scope="module")
def dash(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Dashboard]:
    base = tmp_path_factory.mktemp("leaves")
    proc = start_controller(base / "state", rig=RIG)
    try:
        with ControllerClient(ClientOptions(connect=(proc.endpoint,), rig_name=RIG,
                                            connect_timeout_s=60.0)) as probe:
            assert wait_until(lambda: answers(probe), 180.0, poll_s=0.5), proc.log()
        opts = DashboardOptions(connect=(proc.endpoint,), rig_name=RIG, port=free_port(),
                                verbose=False, recordings_dir=base / "rec",
                                candidates_dir=base / "cand")
        with Dashboard(opts) as d:
            yield d
    finally:
        proc.stop()


def test_a_browser_gone_before_its_panels_are_built_is_a_departure(
        dash: Dashboard, caplog: pytest.LogCaptureFixture) -> None:
    assert dash.server is not None
    handles = []
    dash.server.on_client_connect(handles.append)
    with connected(dash):
        wait_for(lambda: handles, 20.0, "the test's connect callback never ran")
    gone = handles[-1]
    wait_for(lambda: gone.client_id not in dash.server.get_clients(), 20.0,
             "viser never noticed the browser leave")
    with caplog.at_level(logging.INFO, logger="server.dashboard.app"):
        dash._on_client_connect(gone)  # what viser's pool runs when the close wins the race
    assert any("left while its panels were built" in r.getMessage() for r in caplog.records)
    assert gone.client_id not in dash.candidates.panels  # nothing kept for the departed
    assert gone.client_id not in dash.candidates.guides
    # the next browser still gets its own panel
    with connected(dash):
        ids = set(dash.server.get_clients())
        wait_for(lambda: ids & set(dash.candidates.panels), 30.0, "no panel for the next one")


def test_a_removed_handle_is_a_departure_only_for_a_browser_gone() -> None:
    """The other face of the race (seen in a suite run): viser raises RuntimeError "Cannot
    assign ... on a removed GuiTabGroupHandle" when the browser left mid-build."""
    from types import SimpleNamespace

    from server.dashboard.app import build_or_depart

    client = SimpleNamespace(client_id=7)
    departed: list[int] = []

    def build() -> None:
        raise RuntimeError("Cannot assign to '_tab_icons_html' on a removed GuiTabGroupHandle.")

    gone = SimpleNamespace(get_clients=lambda: {})
    build_or_depart(gone, client, build, lambda: departed.append(7))  # type: ignore[arg-type]
    assert departed == [7]
    here = SimpleNamespace(get_clients=lambda: {7: client})
    with pytest.raises(RuntimeError, match="removed GuiTabGroupHandle"):
        build_or_depart(here, client, build, lambda: departed.append(8))  # type: ignore[arg-type]
    assert departed == [7]

"""The `dobtune identify` command (offline on the simulated rig; `--connect` without a
controller). Its runs through a controller are in tests/integration/test_identify_remote.py.

Reference: the article's M(s)P(s) (control.md eqs. 33-34), built with python-control.
"""

from __future__ import annotations

import io
import json
import math
from pathlib import Path
from typing import Any

import control
import numpy as np
import pytest

from controller.cli.check import check_main
from controller.cli.frd_files import read_frd_csv
from controller.cli.identify import (
    EXIT_ABORTED,
    EXIT_BAD_INPUT,
    EXIT_OK,
    identify_main,
)
from controller.core.config import ARTICLE_MN_DEN, ARTICLE_PN_DEN, ARTICLE_PN_NUM
from controller.ident.spec import IdentifySpec
from controller.sim.sim_rig import SimRig

MP = control.tf([1.0], list(ARTICLE_MN_DEN)) * control.tf(
    list(ARTICLE_PN_NUM), list(ARTICLE_PN_DEN)
)
WN_TRUE = math.sqrt(1935.0)  # rad/s: M(s)P(s) = 1935 / (s^2 + 62.2 s + 1935)
ZETA_TRUE = 62.2 / (2.0 * WN_TRUE)


def _mp(freq_hz: np.ndarray) -> np.ndarray:
    resp = control.frequency_response(MP, 2.0 * np.pi * freq_hz)
    return np.asarray(resp.complex).ravel()


SHORT: dict[str, Any] = {"points_per_decade": 3, "min_measure_s": 1.0}


def _cli(tmp_path: Path, **kw: Any) -> tuple[int, str, str]:
    """identify_main with the options of a short run; spec fields and options in `kw`."""
    out, err = io.StringIO(), io.StringIO()
    spec_fields: dict[str, Any] = {
        "mode": "open",
        "signal": "sine",
        "f_min_hz": 0.5,
        "f_max_hz": 12.0,
        "positions": 2,
        "amplitude_deg_s": 10.0,
        **SHORT,
    }
    args: dict[str, Any] = {
        "plant": "sim",
        "connect": None,
        "rig_name": None,
        "out_dir": tmp_path / "id",
        "as_json": False,
    }
    for name, value in kw.items():
        (spec_fields if name in spec_fields else args)[name] = value
    code = identify_main(spec_fields=spec_fields, out=out, err=err, **args)
    return code, out.getvalue(), err.getvalue()


def test_cli_writes_files_readable_by_check(tmp_path: Path) -> None:
    code, text, err = _cli(tmp_path, as_json=True)
    assert code == EXIT_OK, err
    summary = json.loads(text)
    assert summary["complete"] is True
    fit = summary["fit"]
    assert fit["natural_freq_hz"] == pytest.approx(WN_TRUE / (2 * math.pi), rel=0.1)
    assert fit["zeta"] == pytest.approx(ZETA_TRUE, rel=0.1)
    assert fit["natural_freq_std_hz"] > 0 and fit["zeta_std"] > 0
    assert summary["agreement_freq_hz"] == pytest.approx(summary["f_max_hz"], rel=0.05)
    r31 = summary["recommended_cutoff_hz"]["q31"]
    assert r31 > 0 and "q20" in summary["recommended_cutoff_hz"]
    assert "[100%] done" in err  # progress line
    out_dir = tmp_path / "id"
    assert json.loads((out_dir / "summary.json").read_text()) == summary
    csvs = [out_dir / "pos0_0deg.csv", out_dir / "pos1_180deg.csv"]
    for k, path in enumerate(csvs):
        data = read_frd_csv(path)
        assert data.coherence is not None and np.all(data.coherence > 0.99)
        assert data.freq_hz.size == summary["n_frequencies"]
        low = data.freq_hz <= 5.0
        assert np.allclose(data.response[low], _mp(data.freq_hz[low]), rtol=0.1)
        raw = np.load(out_dir / f"raw_pos{k}.npz")
        assert {"t_s", "u_deg_s", "w_deg_s", "x_deg_s", "pos_deg", "phase"} <= set(raw.files)
        assert raw["u_deg_s"].size == raw["w_deg_s"].size > 10000 and bool(raw["complete"])
    # `dobtune check` with the fitted configuration and the curves: the recommendation is
    # accepted and 1.5x it is rejected
    fitted = out_dir / summary["fitted_config"]
    out = io.StringIO()
    assert check_main(fitted, "q31", r31, csvs, True, out) == 0, out.getvalue()
    assert json.loads(out.getvalue())["verdict"] == "accept"
    out = io.StringIO()
    # Above the recommended maximum: a caution (exit 3) that says so, or a rejection.
    assert check_main(fitted, "q31", 1.5 * r31, csvs, True, out) in (1, 3)
    data = json.loads(out.getvalue())
    assert data["verdict"] != "accept" and data["reasons"]


def test_cli_table(tmp_path: Path) -> None:
    code, text, _ = _cli(tmp_path, positions=1, signal="multisine", mode="closed")
    assert code == EXIT_OK
    assert "natural frequency" in text and "damping" in text and "+-" in text
    assert "recommended max Q cut-off" in text and "Q31" in text
    assert "curves agree" not in text  # one position: nothing to compare


def test_cli_abort_exits_1_with_partial_data(tmp_path: Path) -> None:
    class Slip:
        """A units slip in the drive: the load moves twice what is commanded."""

        def __init__(self) -> None:
            self.rig = SimRig()

        def read(self) -> tuple[float, float]:
            return self.rig.read()

        def step(self, command_deg_s: float) -> None:
            self.rig.step(2.0 * command_deg_s)

    code, text, err = _cli(tmp_path, as_json=True, rig_factory=Slip)
    assert code == EXIT_ABORTED
    assert "aborted" in err and "position window" in err
    summary = json.loads(text)
    assert summary["complete"] is False and "position window" in summary["abort_reason"]
    assert summary["positions"][0]["complete"] is False
    assert (tmp_path / "id" / "raw_pos0.npz").exists()
    assert json.loads((tmp_path / "id" / "summary.json").read_text())["complete"] is False


@pytest.mark.parametrize(
    ("kw", "needle"),
    [
        ({"f_min_hz": -1.0}, "--f-min: f_min_hz"),
        ({"f_max_hz": 0.05}, "--f-min: f_min_hz"),
        ({"mode": "sideways"}, "--mode: mode"),
        ({"signal": "chirp"}, "--signal: signal"),
        ({"positions": 0}, "--positions: positions"),
        ({"amplitude_deg_s": -2.0}, "--amplitude: amplitude_deg_s"),
        ({"amplitude_deg_s": 50.0}, "--amplitude: amplitude_deg_s"),
        ({"plant": "can"}, "--plant"),
        ({"plant": None, "connect": "tcp/127.0.0.1:7447"}, "--rig-name"),
    ],
)
def test_cli_bad_input_names_the_field(tmp_path: Path, kw: dict[str, object], needle: str) -> None:
    code, text, err = _cli(tmp_path, **kw)
    assert code == EXIT_BAD_INPUT
    assert needle in err and text == ""
    assert not (tmp_path / "id").exists()


@pytest.mark.slow
def test_cli_connect_without_a_controller_is_a_clear_error(tmp_path: Path) -> None:
    """--connect to an endpoint where no controller answers: exit 2 naming the option."""
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    code, text, _ = _cli(
        tmp_path, plant=None, connect=f"tcp/127.0.0.1:{port}", rig_name="demo", as_json=True
    )
    assert code == EXIT_BAD_INPUT
    error = json.loads(text)["error"]
    assert error.startswith("--connect:") and "nothing answers at" in error


def test_identify_subcommand_is_registered() -> None:
    import argparse

    from controller.cli.commands import controller_commands

    p = argparse.ArgumentParser()
    controller_commands()["identify"].add_arguments(p)
    args = p.parse_args(
        [
            *("--plant", "sim", "--mode", "closed", "--signal", "multisine"),
            *("--f-min", "0.2", "--f-max", "8", "--positions", "2"),
            *("--amplitude", "5", "--out", "x", "--json"),
        ]
    )
    assert (args.plant, args.mode, args.signal, args.f_min_hz, args.f_max_hz) == (
        "sim",
        "closed",
        "multisine",
        0.2,
        8.0,
    )
    assert (args.positions, args.amplitude_deg_s, args.out, args.json) == (2, 5.0, Path("x"), True)


def test_identify_options_are_the_specs_with_their_defaults() -> None:
    """The options generated from the spec's metadata: the same flags, defaults and
    placeholders as ever, and the spec's help text."""
    import argparse

    from controller.cli.commands import controller_commands

    p = argparse.ArgumentParser()
    controller_commands()["identify"].add_arguments(p)
    args = p.parse_args([])
    assert (args.mode, args.signal, args.f_min_hz, args.f_max_hz) == (
        "open", "multisine", 0.1, 20.0)
    assert (args.positions, args.amplitude_deg_s) == (3, 10.0)
    assert (args.plant, args.connect, args.out, args.json) == (None, None, Path("identify-out"),
                                                               False)
    usage = " ".join(p.format_usage().split())
    for option in ("[--mode open|closed]", "[--signal sine|multisine]", "[--f-min HZ]",
                   "[--f-max HZ]", "[--positions N]", "[--amplitude DEG_S]"):
        assert option in usage, usage
    assert "largest excitation amplitude" in p.format_help()
    spec = IdentifySpec(**{f: getattr(args, f) for f in (
        "mode", "signal", "f_min_hz", "f_max_hz", "positions", "amplitude_deg_s")})
    assert spec == IdentifySpec()  # the command's defaults are the spec's



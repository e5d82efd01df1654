"""`dobtune check` command body: exit codes, output, errors naming file and line."""

from __future__ import annotations

import io
import json
from pathlib import Path

import msgspec
import numpy as np
import pytest
from old_loop import OLD_LOOP, OLD_LOOP_PATH

from controller.cli.check import check_main
from controller.cli.frd_files import write_frd_csv
from controller.core.config import LoopConfig, config_to_builtins
from controller.gate.loop_model import nominal_continuous_response
from controller.gate.verdict import EXIT_CODES

KEYS = {
    "verdict",
    "reasons",
    "gain_margin_db",
    "gain_margin_up_db",
    "gain_reduction_margin_db",
    "phase_margin_deg",
    "peak_sensitivity_db",
    "small_gain_peak",
    "max_pole_radius",
    "recommended_max_cutoff_hz",
    "config",
}


def _run(
    as_json: bool = False,
    *,
    config_path: Path | None = None,
    q_type: str | None = None,
    cutoff_hz: float | None = None,
    frd_paths: list[Path] | None = None,
) -> tuple[int, str]:
    out = io.StringIO()
    code = check_main(config_path, q_type, cutoff_hz, frd_paths or [], as_json, out)
    return code, out.getvalue()


def test_default_config_is_accepted_with_a_table() -> None:
    code, text = _run()
    assert code == 0
    assert "verdict: ACCEPT" in text
    assert "phase margin" in text and "recommended max cut-off (q31)" in text


def test_the_default_loop_states_both_gain_margins_positive() -> None:
    """Issue 33 item 2: the demo's default loop is conditionally stable; `dobtune check` names
    the gain margin up and the gain-reduction margin down, both positive, each at its
    crossing, and its JSON carries both beside python-control's signed pick (kept for the
    scripts that read it). The numbers are the analysis' (python-control's, see
    tests/test_analysis.py::test_gain_margins_up_and_down_agree_with_python_control)."""
    from controller.gate.analysis import analyse

    m = analyse(LoopConfig()).margins
    assert m.gain_margin_db < 0 < m.gain_reduction_margin_db < m.gain_margin_up_db
    code, text = _run()
    assert code == 0
    head = (f"speed loop: gain margin {m.gain_margin_up_db:.1f} dB up, gain-reduction margin "
            f"{m.gain_reduction_margin_db:.1f} dB down")
    assert head in text, text
    assert f"{m.gain_margin_db:.1f} dB" not in text, text  # no signed "-25.8 dB" left
    assert f"{m.gain_reduction_margin_hz:.3g} Hz" in text
    assert f"{m.gain_margin_up_hz:.3g} Hz" in text
    code, out = _run(True)
    data = json.loads(out)
    assert data["gain_margin_up_db"] == pytest.approx(m.gain_margin_up_db)
    assert data["gain_reduction_margin_db"] == pytest.approx(m.gain_reduction_margin_db)
    assert data["gain_margin_db"] == pytest.approx(m.gain_margin_db)


def test_json_output_has_the_keys_and_the_effective_config(tmp_path: Path) -> None:
    path = tmp_path / "cfg.json"
    # A softer variant of the earlier default loop (examples/loop_cv_0.5_55.json).
    path.write_text(json.dumps(config_to_builtins(OLD_LOOP.with_(cv_kp=0.45))), encoding="utf-8")
    code, text = _run(True, config_path=path, q_type="q20", cutoff_hz=0.5)
    data = json.loads(text)
    assert code == 0 and data["verdict"] == "accept", data["reasons"]
    assert data.keys() >= KEYS
    cfg = data["config"]
    assert (cfg["cv_kp"], cfg["q_type"], cfg["q_cutoff_hz"]) == (0.45, "q20", 0.5)
    assert cfg["q_tau_s"] == pytest.approx(0.10243 / 0.5, rel=1e-4)
    assert "simulated rig model" in data["knowledge"]
    assert data["recommended_max_cutoff_hz"] > 0


def test_caution_exits_3_and_names_the_loop_and_the_evidence(tmp_path: Path) -> None:
    # The procedure's PI loop, written out, with Q20 at 30 Hz: stable with margins, but noisy,
    # above the recommended cut-off, and it rings after a reversal (a transient: a caution).
    path = tmp_path / "pi.json"
    pi = LoopConfig(cv_kp=1.35, cv_ki_per_s=10.8, pos_kp_per_s=9.0, pos_ki_per_s=3.5)
    path.write_text(json.dumps(config_to_builtins(pi)), encoding="utf-8")
    code, text = _run(config_path=path, q_type="q20", cutoff_hz=30.0)
    assert code == 3, text
    assert "verdict: CAUTION" in text
    assert "caution: noise to command gain" in text and "plant model" in text
    assert "above the recommended maximum" in text
    assert "caution: nonlinear check: ringing after a velocity reversal" in text
    code, text = _run(True, config_path=path, q_type="q20", cutoff_hz=30.0)
    data = json.loads(text)
    assert code == 3 and data["verdict"] == "caution" and not data["rejections"]


def test_sustained_chatter_exits_1_and_names_the_conditional_stability() -> None:
    """Issue 22: the earlier default loop with Q31 at 15 Hz (gain margin -10.8 dB, chatter at
    standstill that does not decay) is rejected, not cautioned, and says why."""
    code, text = _run(config_path=OLD_LOOP_PATH, cutoff_hz=15.0)
    assert code == EXIT_CODES["reject"] == 1, text
    assert "verdict: REJECT" in text
    assert "reject: nonlinear check: chatter at standstill" in text and "sustained" in text
    assert "conditionally stable: a gain reduction of 10.8 dB destabilises the speed loop" in text
    # At 5 Hz the same: the linear margins stay cautions beside the rejection.
    code, text = _run(True, config_path=OLD_LOOP_PATH, cutoff_hz=5.0)
    data = json.loads(text)
    assert code == 1 and data["verdict"] == "reject"
    assert any(r.startswith("nonlinear check: chatter") for r in data["rejections"])
    assert any("whole servo, plant model" in r for r in data["cautions"])


def test_rejected_candidate_exits_1_with_reasons(tmp_path: Path) -> None:
    path = tmp_path / "cfg.json"
    # The earlier default loop with 16x its Kp (gain margin 22 dB): unstable on the model.
    path.write_text(json.dumps(config_to_builtins(OLD_LOOP.with_(cv_kp=8.0))), encoding="utf-8")
    code, text = _run(config_path=path)
    assert code == 1
    assert "verdict: REJECT" in text and "reject: closed-loop pole radius" in text
    code, text = _run(True, config_path=path)
    data = json.loads(text)
    assert code == 1 and data["verdict"] == "reject" and data["rejections"]


def test_knowledge_file_is_the_evidence(tmp_path: Path) -> None:
    """A plant with 15x the model's gain: the default config is unstable on it."""
    from controller.core.config import NominalModel
    from controller.gate.knowledge import BoundRecord, KnowledgeRecord

    n = NominalModel()
    a, b, c = n.pn_num
    k = KnowledgeRecord(
        version=7, source="rig file",
        model=NominalModel(mn_den=n.mn_den, pn_num=(15 * a, 15 * b, 15 * c), pn_den=n.pn_den),
        bound=BoundRecord(low_freq_fraction=0.2, unity_freq_hz=40.0, high_freq_fraction=4.0),
    )
    path = tmp_path / "knowledge.json"
    path.write_bytes(msgspec.json.encode(k))
    out = io.StringIO()
    code = check_main(None, None, None, [], True, out, path)
    data = json.loads(out.getvalue())
    assert code == 1 and "plant knowledge v7 (rig file" in data["knowledge"]
    path.write_text('{"version": 1, "bound": {"low_freq_fraction": 2.0, "unity_freq_hz": 1}}')
    out = io.StringIO()
    assert check_main(None, None, None, [], False, out, path) == 2
    assert "low_freq_fraction" in out.getvalue() and str(path) in out.getvalue()
    path.write_text('{"versoin": 1}')
    out = io.StringIO()
    assert check_main(None, None, None, [], False, out, path) == 2
    assert "versoin" in out.getvalue()


def test_measured_files_feed_the_gate(tmp_path: Path) -> None:
    f = np.geomspace(0.01, 400.0, 200)
    h = 1.6 * nominal_continuous_response(LoopConfig().nominal, f)
    write_frd_csv(tmp_path / "gain160.csv", f, h)
    code, text = _run(True, frd_paths=[tmp_path / "gain160.csv"])
    data = json.loads(text)
    assert [s["name"] for s in data["sources"]] == ["commissioning bound", "gain160"]
    assert data["sources"][1]["band_hz"] == [pytest.approx(0.01), pytest.approx(400.0)]
    assert data["small_gain_peak"] is not None
    assert code == EXIT_CODES[data["verdict"]]


def test_bad_json_names_the_line(tmp_path: Path) -> None:
    path = tmp_path / "cfg.json"
    path.write_text('{\n  "cv_kp": 0.5,\n  "q_type": q31\n}\n', encoding="utf-8")
    code, text = _run(config_path=path)
    assert code == 2
    assert f"{path}:3: invalid JSON" in text


def test_bad_field_names_the_field_and_line(tmp_path: Path) -> None:
    path = tmp_path / "cfg.json"
    path.write_text('{\n  "rate_hz": 1000,\n  "cv_kp": -1\n}\n', encoding="utf-8")
    code, text = _run(config_path=path)
    assert code == 2
    assert f"{path}:3" in text and "cv_kp" in text
    code, text = _run(True, config_path=tmp_path / "missing.json")
    assert code == 2 and "cannot read config" in json.loads(text)["error"]


def test_bad_overrides_and_bad_response_file(tmp_path: Path) -> None:
    code, text = _run(q_type="q99")
    assert code == 2 and "--q" in text and "q99" in text
    code, text = _run(cutoff_hz=600.0)
    assert code == 2 and "--cutoff-hz" in text and "Nyquist" in text
    bad = tmp_path / "bad.csv"
    bad.write_text("freq_hz,mag_db,phase_deg\n1,0,0\n2,zero,0\n", encoding="utf-8")
    code, text = _run(frd_paths=[bad])
    assert code == 2 and f"{bad}:3:" in text
    code, text = _run(frd_paths=[tmp_path / "nope.csv"])
    assert code == 2 and "nope.csv" in text

"""Measured responses for the gate: CSV files -> MeasuredResponse (the bad files, whose errors
name file and line, are tests/test_frd_estimate.py's table, read by both readers)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from controller.cli.frd_files import load_measured, measured_from_csv, write_frd_csv
from controller.gate.frd import measured_from_model


def _write(tmp_path: Path, text: str, name: str = "resp.csv") -> Path:
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


GOOD = "freq_hz,mag_db,phase_deg,coherence\n1.0,0.0,-10\n2.0,-6.0,-20,0.5\n"


def test_round_trip_with_the_project_writer(tmp_path: Path) -> None:
    f = np.geomspace(0.1, 100.0, 50)
    h = 1.0 / (1 + 1j * f / 7.0) ** 2
    write_frd_csv(tmp_path / "pos_120deg.csv", f, h)
    (m,) = load_measured([tmp_path / "pos_120deg.csv"])
    assert m.name == "pos_120deg" and not m.sampled
    np.testing.assert_allclose(m.freq_hz, f, rtol=1e-9)
    np.testing.assert_allclose(m.response, h, rtol=1e-8)


def test_coherence_filter_and_unique_names(tmp_path: Path) -> None:
    a = _write(tmp_path, GOOD.replace("-10\n", "-10,0.9\n"))
    sub = tmp_path / "sub"
    sub.mkdir()
    b = _write(sub, GOOD.replace("-10\n", "-10,0.9\n"))
    m1, m2 = load_measured([a, b])
    assert (m1.name, m2.name) == ("resp", "resp#2")
    with pytest.raises(ValueError, match="fewer than 2 points"):
        measured_from_csv(a, min_coherence=0.8)
    m = measured_from_csv(a, min_coherence=0.4)
    assert m.response[1] == pytest.approx(10 ** (-6 / 20) * np.exp(-1j * np.radians(20)))


def test_model_variant() -> None:
    f = np.array([0.0001, 7.0])
    wn = 2 * np.pi * 7.0
    m = measured_from_model("resonant", f, [2.0], [1 / wn**2, 2 * 0.05 / wn, 1.0])
    assert m.response[0] == pytest.approx(2.0, rel=1e-5)
    assert m.response[1] == pytest.approx(2.0 / (2j * 0.05))  # Q = 1/(2 zeta) at resonance
    with pytest.raises(ValueError, match="finite"), np.errstate(all="ignore"):
        measured_from_model("undamped", f, [2.0], [1 / wn**2, 0.0, 1.0])

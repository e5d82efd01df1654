"""`dobtune paper --quick`: the report's sections, its plots, and numbers in it checked against
independent computations."""

from __future__ import annotations

import io
import re
import time
from pathlib import Path

import numpy as np
import pytest
from matplotlib import image
from scipy import optimize

from controller.cli.main import dobtune_main
from controller.cli.paper import figure_file, paper_main
from controller.core.config import LoopConfig

SECTIONS = ("Fig. 8", "Fig. 9", "Fig. 10", "Fig. 11", "Fig. 13", "Fig. 14", "Fig. 15",
            "Fig. 16", "Fig. 17", "Eqs. 28-29", "Disturbances")
VERDICTS = ("agrees", "disagrees", "partly agrees", "no number to compare")


@pytest.fixture(scope="module")
def quick_report(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str, float, str]:
    out = tmp_path_factory.mktemp("paper") / "out"
    err = io.StringIO()
    t0, c0 = time.perf_counter(), time.process_time()
    code = paper_main(out, quick=True, config_path=None, disturbances=[], seed=0, err=err)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    print(f"dobtune paper --quick: {wall:.1f} s wall, {cpu:.1f} s CPU")
    assert code == 0, err.getvalue()
    return out, (out / "report.md").read_text(encoding="utf-8"), cpu, err.getvalue()


def _section(report: str, figure: str) -> str:
    start = report.index(f"## {figure}:")
    nxt = report.find("\n## ", start + 1)
    return report[start : nxt if nxt >= 0 else len(report)]


@pytest.mark.slow
def test_quick_mode_is_quick(quick_report: tuple[Path, str, float, str]) -> None:
    # CPU time of this process (the machine may be shared: wall time is printed).
    assert quick_report[2] < 30.0


def test_every_figure_has_its_section_plot_and_verdict(
    quick_report: tuple[Path, str, float, str],
) -> None:
    out, report, _, _ = quick_report
    for fig in SECTIONS:
        sec = _section(report, fig)
        png = out / figure_file(fig)
        assert f"]({png.name})" in sec
        data = png.read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000, fig
        pixels = np.asarray(image.imread(png))[..., :3]
        # Not blank: a real drawing has a few per cent of non-white pixels (axes, lines, text).
        ink = float(np.mean(np.any(pixels < 0.9, axis=-1)))
        assert pixels.shape[0] > 200 and 0.02 < ink < 0.6, (fig, ink)
        m = re.search(r"\*\*Agreement: ([a-z ]+)\.\*\*", sec)
        assert m is not None and m.group(1) in VERDICTS, fig
        assert "**What we ran.**" in sec and "| " in sec


def test_article_numbers_and_not_reported(quick_report: tuple[Path, str, float, str]) -> None:
    report = quick_report[1]
    f14 = _section(report, "Fig. 14")
    for v in ("0.0231 deg", "0.0207 deg", "0.0052 deg", "0.1 deg", "0.05 deg"):
        assert v in f14
    assert "not reported" in _section(report, "Fig. 8")
    assert "not reported" in _section(report, "Fig. 10")
    assert "8 Hz" in _section(report, "Fig. 11")


def test_fig11_numbers_match_the_closed_form(quick_report: tuple[Path, str, float, str]) -> None:
    """The Q31 row's waterbed of eq. 23 (P = Pn: 1/|1 - Q31|) against the maximum of the
    closed form x^4 (x^2 + 9) / (1 + x^2)^3 found by scipy, and its frequency x / (2 pi tau)."""
    sec = _section(quick_report[1], "Fig. 11")
    row = next(line for line in sec.splitlines() if line.startswith("| Q31 0.5 Hz | nominal"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    peak_db, peak_hz = float(cells[4]), float(cells[5])
    res = optimize.minimize_scalar(lambda x: -(x**4 * (x**2 + 9) / (1 + x**2) ** 3),
                                   bounds=(0.5, 10.0), method="bounded")
    tau = 0.2614 / 0.5  # f_c tau = 0.261407 for Q31 (control.md)
    assert peak_db == pytest.approx(-10 * np.log10(-res.fun), abs=0.01)
    assert peak_hz == pytest.approx(res.x / (2 * np.pi * tau), rel=0.02)
    m = re.search(r"within ([0-9.e+-]+) dB", sec)
    assert m is not None and float(m.group(1)) < 0.01  # python-control's algebra


def test_fig9_offset_matches_the_pi_closed_form(quick_report: tuple[Path, str, float, str]) -> None:
    """Without the DOB, the PI rate loop leaves a position offset -d / (kp ki) after a rate
    disturbance step d (its integrator must hold -d): -5 / (1.35 * 10.8) = -0.343 deg for the
    default Cv, on every plant of Figs. 8 (P = Pn) and 9 (the 40 % + 5 Hz cases)."""
    cfg = LoopConfig()
    rows = []
    for fig in ("Fig. 8", "Fig. 9"):
        sec = _section(quick_report[1], fig)
        rows += [line for line in sec.splitlines() if re.match(r"\| .* \| off \|", line)]
    assert len(rows) == 3
    for row in rows:
        offset = float(row.strip("|").split("|")[-1])
        assert offset == pytest.approx(-5.0 / (cfg.cv_kp * cfg.cv_ki_per_s), rel=0.02)


def test_fig13_spread_matches_the_belt_model(quick_report: tuple[Path, str, float, str]) -> None:
    """The identified spread between 0, 90 and 180 deg against the closed-form belt model
    P_k(s) = (c_k s + k_k) / (J s^2 + (c_k + b) s + k_k) at k (1 + 0.2 cos theta), c (1 + 0.3
    cos theta) (the drive's M is the same at every position and cancels in the spread)."""
    sec = _section(quick_report[1], "Fig. 13")
    rows = [line.strip("|").split("|") for line in sec.splitlines()
            if re.match(r"\| [0-9.]+ \| [+-]", line)]
    assert len(rows) >= 8
    j, b, k, c = 0.08, 5.54, 186.2, 0.386
    checked = 0
    for cells in rows:
        f = float(cells[0])
        if f < 1.5:
            assert float(cells[4]) < 0.2  # they agree below ~1 Hz
            continue
        s_ = 2j * np.pi * f
        mags = [20 * np.log10(abs((c * (1 + 0.3 * x) * s_ + k * (1 + 0.2 * x))
                                  / (j * s_**2 + (c * (1 + 0.3 * x) + b) * s_ + k * (1 + 0.2 * x))))
                for x in (1.0, 0.0, -1.0)]
        ref = max(mags) - min(mags)
        assert float(cells[4]) == pytest.approx(ref, rel=0.15, abs=0.03), f
        checked += 1
    assert checked >= 5
    assert "**Agreement: agrees.**" in sec


def test_progress_is_shown(quick_report: tuple[Path, str, float, str]) -> None:
    progress = quick_report[3].splitlines()
    assert len(progress) > 30  # one line per run, plot and check
    assert any("Fig. 10: position-loop DOB" in line for line in progress)
    assert progress[-1].endswith("11 PNG files") and "report.md" in progress[-1]


def test_command_is_registered_and_bad_input_exits_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert dobtune_main(["paper", "--out", str(tmp_path), "--disturbance", "earthquake"]) == 2
    assert "disturbance" in capsys.readouterr().err
    bad = tmp_path / "cfg.json"
    bad.write_text('{"cv_kp": -1}')
    assert dobtune_main(["paper", "--out", str(tmp_path), "--config", str(bad)]) == 2
    assert "cv_kp" in capsys.readouterr().err

"""`dobtune identify --from`: an identification run recorded, then analysed again.

The run is executed here as the controller's tick executes it (the same `ExcitationProgram`,
`ServoLoop` and simulated rig, one state sample per tick, the program's start stamped with
its sequence number), recorded with the same `Recorder` and `identify` events as `dobtune
record`. The reference is the controller's live analysis (`identify_analysis`) on the
program's own records; the estimates are also checked against the article's M(s)P(s)
(python-control). The controller end to end: tests/test_identify_from_controller.py.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass
from pathlib import Path

import control
import numpy as np
import pytest
from identify_from_common import RTOL, SMALL, same_structure

from controller import protocol as proto
from controller.cli.frd_files import read_frd_csv
from controller.cli.identify import EXIT_BAD_INPUT, EXIT_OK, identify_main
from controller.cli.identify_from import RecordingProblem, recorded_run, status_from_recording
from controller.client.recorder import identify_event
from controller.core.config import ARTICLE_MN_DEN, ARTICLE_PN_DEN, ARTICLE_PN_NUM, LoopConfig
from controller.core.loop import LoopCoefficients, ServoLoop
from controller.core.samples import STATE_COLUMNS
from controller.ident.plan import ProgramPlan, plan_program, to_program
from controller.ident.program import ExcitationProgram
from controller.ident.spec import IdentifySpec
from controller.process.identify_runs import identify_analysis
from controller.recording.mcap_io import Recorder
from controller.sim.sim_rig import SimRig

#: A small plan: 2 stepped sines (1 and 3 Hz) at one position, about 10 s of ticks (the tests
MP = control.tf([1.0], list(ARTICLE_MN_DEN)) * control.tf(
    list(ARTICLE_PN_NUM), list(ARTICLE_PN_DEN)
)


@dataclass
class Ran:
    plan: ProgramPlan
    program: ExcitationProgram
    start_seq: int
    start_deg: float
    columns: dict[str, list[float]]
    first_seq: int


def _run(spec: IdentifySpec, before: int = 300, after: int = 300) -> Ran:
    """Hold, then the program, then hold: the runtime's tick, one sample per tick."""
    cfg = LoopConfig()
    rig = SimRig(rate_hz=cfg.rate_hz, seed=3, initial_position_deg=2.0)
    loop = ServoLoop(LoopCoefficients.build(cfg))
    cols: dict[str, list[float]] = {c: [] for c in STATE_COLUMNS}
    plan: ProgramPlan | None = None
    prog: ExcitationProgram | None = None
    start_seq = -1
    start_deg = 0.0
    seq = 0
    hold = 2.0
    ts = 1.0 / cfg.rate_hz
    while True:
        seq += 1
        t = seq * ts
        pos, w = rig.read()
        if prog is None and plan is None and seq == before:
            start_deg = pos  # the controller plans from the last position it read
            plan = plan_program(spec, cfg, start_deg)
            prog = to_program(plan)
            start_seq = prog.start_seq = seq + 1  # taken by the loop at the next tick
        if prog is not None and seq >= start_seq and not prog.over:
            u = prog.step(t, pos, w, loop)
            ref, r = prog.ref, prog.r
            if prog.over:
                hold = pos
        else:
            ref = hold
            u = loop.tick(ref, 0.0, pos, w)
            r = loop.speed_ref_deg_s
        rig.step(u)
        for name, v in zip(STATE_COLUMNS,
                           (t, ref, pos, w, r, u, loop.d_hat, ref - pos), strict=True):
            cols[name].append(v)
        if prog is not None and prog.over and seq >= start_seq + prog.n_done + after:
            break
    assert plan is not None and prog is not None and prog.state == "done"
    return Ran(plan, prog, start_seq, start_deg, cols, 1)


def _status(ran: Ran, state: str = "done", abort_reason: str = "",
            **run: object) -> proto.IdentifyStatus:
    fields = dict(spec=ran.plan.spec, config=ran.plan.config, start_deg=ran.start_deg,
                  start_seq=ran.start_seq, ticks_planned=ran.program.n,
                  ticks_done=ran.program.n_done)
    fields.update(run)
    return proto.IdentifyStatus(rig="t", state=state, run_id=1, abort_reason=abort_reason,
                                run=proto.IdentifyRun(**fields))  # type: ignore[arg-type]


def _write(ran: Ran, path: Path, *, drop: tuple[int, int] | None = None,
           skip_first: int = 0, keep: int | None = None,
           events: list[proto.IdentifyStatus] | None = None, batch: int = 20) -> Path:
    """The recording `dobtune record` makes (batches of `batch` ticks); `drop` loses the
    samples [a, b) of seq, `skip_first` starts late, `keep` ends early."""
    n = len(ran.columns["t_s"]) if keep is None else keep
    with Recorder(path, rig="t") as rec:
        st0 = _status(ran, "running")
        for i0 in range(skip_first, n, batch):
            i1 = min(n, i0 + batch)
            seq0 = ran.first_seq + i0
            if drop is not None and seq0 < drop[1] and seq0 + (i1 - i0) > drop[0]:
                continue  # the whole batch lost, as on the wire
            rec.state(proto.state_batch(
                rig="t", seq0=seq0, rate_hz=1000.0, config_version=1,
                columns=[ran.columns[c][i0:i1] for c in STATE_COLUMNS],
                epoch_s=1.7e9, mode="running"))
            if seq0 <= ran.start_seq < seq0 + batch:
                identify_event(rec, st0)
        for st in events if events is not None else [_status(ran, "done")]:
            identify_event(rec, st)
    return path


@pytest.fixture(scope="module")
def ran() -> Ran:
    return _run(SMALL)


@pytest.fixture(scope="module")
def live(ran: Ran) -> dict[str, object]:
    """The controller's analysis of the run, on the program's own records."""
    p = ran.program
    return identify_analysis(ran.plan, p.rec_u, p.rec_w, p.rec_pos, p.n_done, None, 0.0)


def test_from_gives_the_live_estimates(ran: Ran, live: dict[str, object],
                                       tmp_path: Path) -> None:
    path = _write(ran, tmp_path / "id.mcap")
    st = status_from_recording(path)
    assert st.state == "done" and st.run_id == 1 and st.abort_reason == ""
    (pos,) = st.positions
    (ref,) = live["positions"]  # type: ignore[misc]
    assert pos.complete and len(pos.freq_hz) >= 2
    assert (pos.points_done, pos.points_total) == (ref.points_done, ref.points_total)
    for name in ("freq_hz", "mag_db", "phase_deg", "coherence"):
        np.testing.assert_allclose(getattr(pos, name), getattr(ref, name), rtol=RTOL,
                                   atol=1e-12, err_msg=name)
    assert st.natural_freq_hz == pytest.approx(live["natural_freq_hz"], rel=RTOL)
    assert st.zeta == pytest.approx(live["zeta"], rel=RTOL)
    assert st.recommended_cutoff_hz == pytest.approx(live["recommended_cutoff_hz"], rel=RTOL)
    ours, theirs = json.loads(st.summary_json), json.loads(str(live["summary_json"]))
    same_structure(ours["fit"], theirs["fit"], RTOL)
    same_structure(ours["gate_checks"], theirs["gate_checks"], RTOL)
    # independent reference: the article's M(s)P(s) (the simulated rig's low-frequency model)
    f = np.asarray(pos.freq_hz)
    h = 10.0 ** (np.asarray(pos.mag_db) / 20.0) * np.exp(1j * np.radians(pos.phase_deg))
    mp = np.asarray(control.frequency_response(MP, 2 * np.pi * f).complex).ravel()
    assert np.max(np.abs(20 * np.log10(np.abs(h / mp)))) < 1.5
    assert np.max(np.abs(np.degrees(np.angle(h / mp)))) < 10.0


def test_the_command_writes_what_identify_connect_writes(ran: Ran, live: dict[str, object],
                                                         tmp_path: Path) -> None:
    path = _write(ran, tmp_path / "id.mcap")
    out, err = io.StringIO(), io.StringIO()
    code = identify_main(None, None, None, {}, tmp_path / "out", True, out, err,
                         from_file=path)
    assert code == EXIT_OK, err.getvalue()
    summary = json.loads(out.getvalue())
    assert summary["complete"] is True and summary["plant"] == "controller"
    assert (tmp_path / "out" / "summary.json").exists()
    assert (tmp_path / "out" / "config_fitted.json").exists()
    frd = read_frd_csv(tmp_path / "out" / summary["positions"][0]["csv"])
    (ref,) = live["positions"]  # type: ignore[misc]
    np.testing.assert_allclose(frd.freq_hz, ref.freq_hz, rtol=1e-6)
    np.testing.assert_allclose(frd.mag_db, ref.mag_db, atol=1e-4)
    # the readable table
    out2 = io.StringIO()
    assert identify_main(None, None, None, {}, tmp_path / "out2", False, out2, io.StringIO(),
                         from_file=path) == EXIT_OK
    assert "fit Mn Pn" in out2.getvalue() and "recommended max Q cut-off" in out2.getvalue()


def _problem(path: Path) -> str:
    with pytest.raises(RecordingProblem) as info:
        recorded_run(path)
    text = str(info.value)
    assert str(path) in text
    return text


def test_a_recording_without_an_identification_run(ran: Ran, tmp_path: Path) -> None:
    path = _write(ran, tmp_path / "plain.mcap", events=[], keep=200)
    assert "no identification run in this recording" in _problem(path)
    # through the command: exit 2, the message names the flag and the problem
    out, err = io.StringIO(), io.StringIO()
    assert identify_main(None, None, None, {}, tmp_path / "o", False, out, err,
                         from_file=path) == EXIT_BAD_INPUT
    assert "--from:" in err.getvalue() and "no identification run" in err.getvalue()


def test_a_gap_inside_the_run(ran: Ran, tmp_path: Path) -> None:
    a = ran.start_seq + 2000
    path = _write(ran, tmp_path / "gap.mcap", drop=(a, a + 1))
    text = _problem(path)
    assert "a gap inside the run: 20 sample(s) lost" in text
    lost0 = a - (a - ran.first_seq) % 20
    assert f"seq {lost0}-{lost0 + 19}" in text


def test_a_gap_outside_the_run_does_not_matter(ran: Ran, tmp_path: Path) -> None:
    path = _write(ran, tmp_path / "gap_before.mcap", drop=(50, 51))
    assert recorded_run(path).run.ticks_done == ran.program.n


def test_a_recording_that_starts_late_or_ends_early(ran: Ran, tmp_path: Path) -> None:
    late = _write(ran, tmp_path / "late.mcap", skip_first=ran.start_seq - ran.first_seq + 40)
    assert "tick(s) after the run began" in _problem(late)
    end = ran.start_seq + ran.program.n - 1
    early = _write(ran, tmp_path / "early.mcap", keep=end - ran.first_seq - 100)
    assert "before the run ended" in _problem(early)
    # the recorder last saw it running: not over
    running = _write(ran, tmp_path / "running.mcap", events=[_status(ran, "running")])
    assert "had not ended when the recording stopped" in _problem(running)


def test_a_plan_that_no_longer_matches(ran: Ran, tmp_path: Path) -> None:
    # another plan length: the tick count differs
    longer = _write(ran, tmp_path / "longer.mcap",
                    events=[_status(ran, "done", ticks_planned=ran.program.n + 5)])
    assert "the planning code changed" in _problem(longer)
    # the same length, another offset on one excitation tick
    i = ran.plan.seg_end[0] - 500
    assert ran.plan.kind[i] == 1
    cols = dict(ran.columns)
    k = ran.start_seq - ran.first_seq + i
    cols["speed_ref_deg_s"] = [*cols["speed_ref_deg_s"]]
    cols["speed_ref_deg_s"][k] += 1e-3
    other = Ran(ran.plan, ran.program, ran.start_seq, ran.start_deg, cols, ran.first_seq)
    text = _problem(_write(other, tmp_path / "other.mcap"))
    assert "does not follow the plan rebuilt from its spec" in text
    assert f"at tick {i} (seq {ran.start_seq + i})" in text


def test_an_aborted_run_gives_the_partial_estimates(ran: Ran, tmp_path: Path) -> None:
    # the run as if aborted after its first segment (inside it if there is only one): partial
    # estimates, no fit
    n_seg = ran.plan.n_segments
    n_done = ran.plan.seg_end[0] + (10 if n_seg > 1 else -10)
    p = ran.program
    live = identify_analysis(ran.plan, p.rec_u, p.rec_w, p.rec_pos, n_done, "request", 0.0)
    path = _write(ran, tmp_path / "abort.mcap",
                  events=[_status(ran, "aborted", "request", ticks_done=n_done)])
    st = status_from_recording(path)
    assert st.state == "aborted" and st.abort_reason == "request"
    (pos,) = st.positions
    (ref,) = live["positions"]  # type: ignore[misc]
    assert not pos.complete and st.natural_freq_hz is None
    assert pos.points_done == ref.points_done == (1 if n_seg > 1 else 0)
    assert len(pos.mag_db) == len(ref.mag_db)
    np.testing.assert_allclose(pos.mag_db, ref.mag_db, rtol=RTOL)
    out, err = io.StringIO(), io.StringIO()
    assert identify_main(None, None, None, {}, tmp_path / "o", True, out, err,
                         from_file=path) == 1
    assert "identification aborted: request" in err.getvalue()


def test_from_refuses_other_sources_and_spec_flags(tmp_path: Path) -> None:
    err = io.StringIO()
    assert identify_main(None, "tcp/127.0.0.1:7447", "r", {}, tmp_path, False, io.StringIO(),
                         err, from_file=tmp_path / "x.mcap") == EXIT_BAD_INPUT
    assert "--from is exclusive" in err.getvalue()
    err = io.StringIO()
    assert identify_main(None, None, None, {"f_min_hz": 0.5}, tmp_path, False, io.StringIO(),
                         err, from_file=tmp_path / "x.mcap") == EXIT_BAD_INPUT
    assert "remove --f-min" in err.getvalue()
    err = io.StringIO()
    assert identify_main(None, None, None, {}, tmp_path, False, io.StringIO(), err,
                         from_file=tmp_path / "missing.mcap") == EXIT_BAD_INPUT
    assert "missing.mcap" in err.getvalue()

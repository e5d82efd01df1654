"""The real-time runtime: scheduling (fake clock), sample hand-off, requests, e-stop, faults."""

from __future__ import annotations

import itertools
import subprocess
import sys
import threading
import tracemalloc
from collections.abc import Sequence
from typing import Any

import pytest
from helpers import FakeClock

from controller.core.config import LoopConfig
from controller.core.loop import LoopCoefficients, ServoLoop
from controller.core.trajectory import Trajectory
from controller.core.watchdog import WatchdogLimits
from controller.ident.program import ExcitationProgram
from controller.process.requests import (
    AbortProgram,
    ApplyCoefficients,
    EStop,
    ResetFault,
    RunProgram,
    SetTrajectory,
    Start,
    Stop,
)
from controller.process.runtime import (
    COLUMNS,
    ESTOP,
    FAULT,
    RUNNING,
    STOPPED,
    Runtime,
    RuntimeOptions,
)
from controller.sim.sim_rig import SimRig

CMD = COLUMNS.index("command_deg_s")


class FakeRig:
    """Records commands; each step costs `cost_s[k]` of fake time; may report a fault."""

    def __init__(self, clock: FakeClock | None = None, cost_s: dict[int, float] | None = None):
        self.clock = clock
        self.cost_s = cost_s or {}
        self.commands: list[float] = []
        self.step_times: list[float] = []
        self.fault: str | None = None
        self.stops = 0
        self.starts = 0
        self.pos = 0.0

    def read(self) -> tuple[float, float]:
        return self.pos, 0.0

    def step(self, command_deg_s: float) -> None:
        k = len(self.commands)
        self.commands.append(command_deg_s)
        if self.clock is not None:
            self.step_times.append(self.clock.now)
            self.clock.now += self.cost_s.get(k, 0.0)
        self.pos += command_deg_s * 1e-3

    def stop(self) -> None:
        self.stops += 1

    def start(self) -> None:
        self.starts += 1


def make_loop(version: int = 1, **cfg: object) -> ServoLoop:
    return ServoLoop(LoopCoefficients.build(LoopConfig(**cfg), version))  # type: ignore[arg-type]


def fake_runtime(
    rig_type: type[FakeRig] = FakeRig, cost_s: dict[int, float] | None = None, **kw: Any
) -> tuple[Runtime, FakeRig]:
    """A runtime on a fake clock (rig.clock) with a fake rig."""
    fc = FakeClock()
    rig = rig_type(fc, cost_s)
    return Runtime(make_loop(), rig, clock=fc.clock, sleep=fc.sleep, **kw), rig


def more(rt: Runtime, ticks: int) -> None:
    """Run `ticks` more ticks after a previous run ended."""
    rt._stop = False
    rt.run(max_ticks=ticks)


def retained_bytes(rt: Runtime, ticks: int = 5000) -> int:
    """Memory still allocated after `ticks` ticks (after 400 ticks of warm-up: every block
    of the ring written once); nobody publishes, the ring is emptied by hand."""
    tick = rt._tick

    def run(k0: int, k1: int) -> None:
        for k in range(k0, k1):
            tick(k * 1e-3)
            rt._ring.consumed = rt._ring.produced

    run(0, 400)
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        run(400, 400 + ticks)
        after = tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
    return after - before


class Collector:
    def __init__(self) -> None:
        self.batches: list[tuple[int, int, str, list[list[float]]]] = []

    def __call__(self, seq0: int, version: int, mode: str, cols: Sequence[list[float]]) -> None:
        self.batches.append((seq0, version, mode, [list(c) for c in cols]))

    def column(self, name: str) -> list[float]:
        i = COLUMNS.index(name)
        return [x for b in self.batches for x in b[3][i]]

    def per_sample(self, what: int) -> list[object]:
        return [b[what] for b in self.batches for _ in b[3][0]]


def run_with_publisher(rt: Runtime, ticks: int) -> Collector:
    col = Collector()
    stop = threading.Event()
    th = threading.Thread(target=rt.publisher, args=(col, stop, 0.001))
    th.start()
    try:
        rt.run(max_ticks=ticks)
    finally:
        stop.set()
        th.join(10.0)
    assert not th.is_alive()
    return col


# -- scheduling ---------------------------------------------------------------------------------


def test_ticks_start_on_the_deadline_grid() -> None:
    rt, rig = fake_runtime()
    rt.run(max_ticks=50)
    starts = [t - rig.step_times[0] for t in rig.step_times[:50]]  # then the shutdown's 0
    for k, t in enumerate(starts):
        assert t == pytest.approx(k * 1e-3, abs=2e-5)
    assert rt.overruns == 0 and rt.skipped_ticks == 0
    # It slept most of each period and spun only the last `spin_s`.
    assert all(s == pytest.approx(1e-3 - 2e-4, abs=5e-5) for s in rig.clock.sleeps[1:])  # type: ignore[union-attr]


def test_overrun_skips_ahead_instead_of_bursting() -> None:
    rt, rig = fake_runtime(cost_s={5: 3.5e-3})  # tick 5 takes 3.5 periods
    rt.run(max_ticks=20)
    t = [x - rig.step_times[0] for x in rig.step_times]
    assert rt.overruns == 1
    assert rt.skipped_ticks == 2  # deadlines at 6 and 7 ms are given up
    # Tick 6 starts right after the long tick (late), tick 7 on the grid again at 9 ms:
    # never two ticks back to back to catch up.
    assert t[6] == pytest.approx(8.5e-3, abs=3e-5)
    assert t[7] == pytest.approx(9.0e-3, abs=3e-5)
    gaps = [b - a for a, b in itertools.pairwise(t[6:20])]
    assert min(gaps) > 0.4e-3
    snap = rt.timing_snapshot()
    assert snap.overruns == 1 and snap.period_max_us > 3000


def test_late_tick_within_a_period_runs_at_once_without_skipping() -> None:
    rt, rig = fake_runtime(cost_s={3: 1.4e-3})
    rt.run(max_ticks=10)
    assert rt.overruns == 1 and rt.skipped_ticks == 0
    t = [x - rig.step_times[0] for x in rig.step_times]
    assert t[4] == pytest.approx(3e-3 + 1.4e-3, abs=3e-5)
    assert t[5] == pytest.approx(5e-3, abs=3e-5)


def test_timing_snapshot_covers_ticks_since_the_previous_one() -> None:
    rt, _ = fake_runtime()
    rt.run(max_ticks=100)
    a = rt.timing_snapshot()
    assert a.samples == 99 and a.ticks == 100
    assert a.period_p50_us == pytest.approx(1000.0, abs=20.0)
    b = rt.timing_snapshot()
    assert b.samples == 0


# -- samples --------------------------------------------------------------------------------------


def test_every_sample_reaches_the_publisher_in_order() -> None:
    rt = Runtime(make_loop(), SimRig(), options=RuntimeOptions(batch_size=20))
    col = run_with_publisher(rt, 500)
    seq = [b[0] for b in col.batches]
    assert seq == list(range(0, 500, 20))
    assert len(col.column("t_s")) == 500
    t = col.column("t_s")
    assert all(b > a for a, b in itertools.pairwise(t))
    assert rt.dropped_samples == 0
    # error = ref - pos, and the loop tracks the sine start.
    ref, pos, err = col.column("ref_deg"), col.column("pos_deg"), col.column("error_deg")
    assert all(e == pytest.approx(r - p) for r, p, e in zip(ref, pos, err, strict=True))


def test_a_stalled_publisher_makes_counted_gaps_not_a_stalled_loop() -> None:
    rt, _ = fake_runtime(options=RuntimeOptions(batch_size=10, ring_blocks=3))
    rt.run(max_ticks=100)  # nobody consumes
    assert rt.ticks == 100
    assert rt.dropped_samples == 100 - 30
    col = Collector()
    stop = threading.Event()
    stop.set()
    rt.publisher(col, stop, 0.001)  # flushes what was kept: the first 30, in order
    assert [b[0] for b in col.batches] == [0, 10, 20]


class NullRig:
    def read(self) -> tuple[float, float]:
        return 0.1, 0.2

    def step(self, command_deg_s: float) -> None:
        pass


def test_the_tick_allocates_nothing_that_stays() -> None:
    # (SimRig refills its noise block every 4096 ticks, outside the loop's control.)
    rt = Runtime(make_loop(), NullRig(), options=RuntimeOptions(ring_blocks=8, batch_size=20))
    retained = retained_bytes(rt)
    assert retained < 4096, retained


# -- requests -------------------------------------------------------------------------------------


def test_new_coefficients_take_effect_at_a_tick_boundary_and_split_the_batch() -> None:
    loop = make_loop(1)
    rt = Runtime(loop, SimRig(), options=RuntimeOptions(batch_size=20))
    new = LoopCoefficients.build(LoopConfig(q_cutoff_hz=1.0), 2)
    col = Collector()
    stop = threading.Event()
    th = threading.Thread(target=rt.publisher, args=(col, stop, 0.001))
    th.start()
    runner = threading.Thread(target=rt.run, kwargs={"max_ticks": 300})
    runner.start()
    assert rt.running.wait(5.0)
    ticket = rt.submit(ApplyCoefficients(new))
    assert ticket.wait(5.0) and ticket.ok
    runner.join(10.0)
    stop.set()
    th.join(10.0)
    versions = col.per_sample(1)
    first_new = versions.index(2)
    assert first_new == ticket.seq
    assert set(versions[:first_new]) == {1} and set(versions[first_new:]) == {2}
    assert all(len(set(b[3][0])) == len(b[3][0]) for b in col.batches)  # homogeneous blocks
    assert rt.config_version == 2


def test_estop_zeroes_the_command_from_the_next_tick_and_stops_the_drive() -> None:
    rt, rig = fake_runtime()
    rt.run(max_ticks=200)
    assert abs(rig.commands[199]) > 0.0
    stops = rig.stops
    rt.estop("test")
    more(rt, 5)
    assert rt.mode == ESTOP and rt.estop_seq == 200 and rt.estop_source == "test"
    assert rig.commands[201:206] == [0.0] * 5  # [200] is the first run's shutdown
    assert rig.stops > stops + 1
    # Start is refused until reset; reset holds the present position.
    t_start = rt.submit(Start())
    t_reset = rt.submit(ResetFault(rt.estop_seq))
    t_start2 = rt.submit(Start())
    more(rt, 1)
    assert not t_start.ok and "reset" in t_start.message
    assert t_reset.ok and rig.starts == 1
    assert t_start2.ok and t_start2.mode == RUNNING


def test_estop_ticket_reports_the_tick_it_took_effect() -> None:
    rt, rig = fake_runtime()
    rt.run(max_ticks=10)
    t = rt.submit(EStop())
    more(rt, 2)
    assert t.ok and t.seq == 10 and t.received_seq == 9 and t.mode == ESTOP
    assert rig.commands[9] != 0.0 and rig.commands[11] == 0.0  # [10]: the shutdown


def test_rig_fault_gives_command_zero_and_keeps_ticking() -> None:
    rt, rig = fake_runtime()
    rt.run(max_ticks=100)
    rig.fault = "no complete feedback for 3 ticks"
    more(rt, 10)
    assert rt.mode == FAULT and rt.fault == rig.fault
    assert rig.commands[101:] == [0.0] * 11 and rig.stops >= 1
    assert rt.ticks == 110


def test_rig_exception_is_a_fault_not_a_crash() -> None:
    class Broken(FakeRig):
        def read(self) -> tuple[float, float]:
            raise OSError("bus gone")

    rt, rig = fake_runtime(Broken)
    rt.run(max_ticks=5)
    assert rt.mode == FAULT and "bus gone" in (rt.fault or "")
    assert rig.commands == [0.0] * 6  # 5 ticks and the shutdown


def test_stop_holds_position_and_start_resumes_the_trajectory() -> None:
    rt, _ = fake_runtime(trajectory=Trajectory(kind="ramp", slope_deg_s=2.0))
    rt.run(max_ticks=50)
    t_stop = rt.submit(Stop())
    more(rt, 1)
    assert t_stop.ok and rt.mode == STOPPED
    assert rt.trajectory.kind == "hold"
    new = Trajectory(kind="hold", offset_deg=1.0)
    t_set = rt.submit(SetTrajectory(trajectory=new))
    t_start = rt.submit(Start())
    more(rt, 1)
    assert t_set.ok and t_start.ok and rt.mode == RUNNING and rt.trajectory == new


def test_shutdown_commands_zero_and_answers_late_requests() -> None:
    rt, rig = fake_runtime()
    rt.run(max_ticks=100)
    assert rig.commands[-1] == 0.0 and rig.stops == 1
    late = rt.submit(Start())
    rt._shutdown()
    assert late.done.is_set() and not late.ok


def test_options_are_validated() -> None:
    with pytest.raises(ValueError, match="spin_s"):
        RuntimeOptions(spin_s=0.002)
    with pytest.raises(ValueError, match="batch_size"):
        RuntimeOptions(batch_size=0)
    with pytest.raises(ValueError, match="mode"):
        Runtime(make_loop(), FakeRig(), mode=ESTOP)


def test_an_estop_arriving_during_a_reset_is_not_lost() -> None:
    rt: Runtime

    class EstopOnStart(FakeRig):
        def start(self) -> None:
            super().start()
            rt.estop("during reset")  # another thread, while the tick re-enables the drive

    rt, _ = fake_runtime(EstopOnStart)
    rt.estop("first")
    rt.run(max_ticks=3)
    assert rt.mode == ESTOP
    reset = rt.submit(ResetFault(rt.estop_seq))
    more(rt, 2)
    assert reset.ok
    assert rt.mode == ESTOP and rt.estop_source == "during reset"


# -- excitation programs (identification inside the loop) ---------------------------------------


def _program(n_move: int = 50, n_exc: int = 200, **kw: object) -> ExcitationProgram:
    """A move to 0 then an open-loop excitation: offset 1 deg/s + 0.5 sin."""
    import math

    exc = [0.5 * math.sin(2.0 * math.pi * k / 100.0) for k in range(n_exc)]
    opts: dict[str, object] = {
        "closed": False,
        "window_deg": 10.0,
        "amplitude_limit": 0.5,
        "max_duration_s": 100.0,
        "command_limit": 100.0,
    }
    opts.update(kw)
    return ExcitationProgram(
        [0] * n_move + [1] * n_exc,
        [1.0] * n_move + [1.0] * n_exc,
        [0.0] * n_move + exc,
        [0.0] * (n_move + n_exc),
        [True] + [False] * (n_move + n_exc - 1),
        [0.0] * (n_move + n_exc),
        [False] * n_move + [True] * n_exc,
        **opts,  # type: ignore[arg-type]
    )


def test_program_runs_in_the_tick_records_every_tick_then_the_rig_runs_as_before() -> None:
    """Issue 33: after a completed identification the rig goes back onto the trajectory it ran
    before (it stayed on a hold while the dashboard still showed the sine), from where the
    program ended, with the bounded approach Start uses (no jump)."""
    rt, rig = fake_runtime()
    before = rt.run_trajectory
    assert before.kind == "sine" and rt.mode == RUNNING
    prog = _program()
    ticket = rt.submit(RunProgram(prog))
    rt.run(max_ticks=300)
    assert ticket.ok and prog.state == "done" and prog.n_done == prog.n == 250
    start = ticket.seq
    # open mode: u = offset + x exactly, tick by tick
    for k in range(50, 250):
        assert rig.commands[start + k] == pytest.approx(1.0 + prog.b[k])
        assert prog.rec_u[k] == rig.commands[start + k]
    assert rt.program is None and rt.mode == RUNNING
    assert rt.trajectory == before == rt.run_trajectory
    assert rt._ramp.active  # the bounded approach from where the program ended
    # A program started while stopped ends stopped (holding): Start resumes the trajectory.
    rt.submit(Stop())
    more(rt, 1)
    prog = _program()
    rt.submit(RunProgram(prog))
    more(rt, 300)
    assert prog.state == "done" and rt.mode == STOPPED and rt.trajectory.kind == "hold"
    assert rt.run_trajectory == before


def test_program_window_hit_aborts_to_a_hold_of_the_present_position() -> None:
    rt, _ = fake_runtime()
    prog = _program(n_exc=2000, window_deg=0.5)  # 1 deg/s leaves +-0.5 deg after ~0.5 s
    ticket = rt.submit(RunProgram(prog))
    rt.run(max_ticks=1500)
    assert ticket.ok and prog.state == "aborted" and prog.limit == "window"
    assert "position window" in prog.reason and 50 < prog.n_done < 1000
    # Stopped (holding where it was): the mode says what the rig does; Start resumes.
    assert rt.program is None and rt.mode == STOPPED
    assert rt.trajectory.kind == "hold" and abs(rt.trajectory.offset_deg) > 0.5


def test_program_duration_limit_and_estop() -> None:
    rt, rig = fake_runtime()
    prog = _program(max_duration_s=0.1)
    rt.submit(RunProgram(prog))
    rt.run(max_ticks=300)
    assert prog.state == "aborted" and prog.limit == "duration"
    # e-stop during a program: command 0 from the very next tick, the program aborted
    rt._stop = False
    prog = _program(n_exc=2000)
    rt.submit(RunProgram(prog))
    rt.run(max_ticks=100)
    assert prog.state == "running"
    rt.estop("test")
    rt._stop = False
    n = len(rig.commands)
    rt.run(max_ticks=5)
    assert prog.state == "aborted" and prog.limit == ESTOP and rt.program is None
    assert rig.commands[n : n + 5] == [0.0] * 5
    # and a new program is refused until reset
    t = rt.submit(RunProgram(_program()))
    more(rt, 1)
    assert not t.ok and "estop" in t.message


def test_a_program_tick_allocates_nothing_that_stays() -> None:
    rt = Runtime(make_loop(), NullRig(), options=RuntimeOptions(ring_blocks=8, batch_size=20))
    prog = _program(n_move=3000, n_exc=3000, window_deg=1e9)
    rt.submit(RunProgram(prog))
    retained = retained_bytes(rt)
    assert prog.state == "running" and prog.n_done == 5400
    assert retained < 4096, retained


def test_program_abort_request_holds_and_stop_stops() -> None:
    rt, rig = fake_runtime()
    prog = _program(n_exc=2000)
    rt.submit(RunProgram(prog))
    rt.run(max_ticks=100)
    t = rt.submit(AbortProgram("test abort"))
    more(rt, 1)
    assert t.ok and prog.state == "aborted" and prog.reason == "test abort"
    assert rt.program is None and rt.mode == STOPPED and rt.trajectory.kind == "hold"
    assert rt.trajectory.offset_deg == pytest.approx(rig.pos, abs=0.01)
    # nothing to abort: ok, says so
    t = rt.submit(AbortProgram())
    more(rt, 1)
    assert t.ok and "no identification" in t.message
    # Stop during a program: aborted, stopped (holding)
    prog = _program(n_exc=2000)
    rt.submit(RunProgram(prog))
    more(rt, 100)
    t = rt.submit(Stop())
    more(rt, 1)
    assert t.ok and prog.state == "aborted" and rt.mode == STOPPED and rt.program is None
    # a program while one runs is refused
    first = _program(n_exc=2000)
    rt.submit(RunProgram(first))
    second = rt.submit(RunProgram(_program()))
    more(rt, 2)
    assert not second.ok and "already running" in second.message and rt.program is first


# -- e-stop ordering, latch, approach after a reset ---------------------------------------------


def test_a_reset_that_arrived_before_an_estop_never_clears_it() -> None:
    rt, _ = fake_runtime()
    rt.estop("first")
    rt.run(max_ticks=2)
    # The reset arrives, then an e-stop; the reset reaches the tick only after the e-stop
    # engaged (the e-stop needs no queue): it is refused and the e-stop holds.
    reset_arrival = rt.next_arrival()
    rt.estop("second", rt.next_arrival())
    with rt.arrival_scope(reset_arrival):
        late_reset = rt.submit(ResetFault(rt.estop_seq))
    more(rt, 2)
    assert not late_reset.ok and "e-stop arrived after this reset" in late_reset.message
    assert rt.mode == ESTOP and rt.estop_source == "second"
    # A reset that arrived after the e-stop works.
    reset = rt.submit(ResetFault(rt.estop_seq))
    more(rt, 2)
    assert reset.ok and rt.mode == STOPPED


def test_a_reset_stamped_before_a_pending_estop_is_refused() -> None:
    rt, _ = fake_runtime()
    rt.estop("first")
    rt.run(max_ticks=2)
    with rt.arrival_scope(rt.next_arrival()):
        reset = rt.submit(ResetFault(rt.estop_seq))
    rt.estop("second")  # pending when the tick serves the reset
    more(rt, 1)
    assert not reset.ok and rt.mode == ESTOP


def test_latch_changes_are_signalled_and_a_restored_latch_holds() -> None:
    rt, rig = fake_runtime()
    rt.restore_latch(ESTOP, "estop key")
    rt.run(max_ticks=5)
    assert rt.mode == ESTOP and rig.stops >= 1 and set(rig.commands) == {0.0}
    assert not rt.submit(Start()).wait(0.0)
    rt.latch_changed.clear()
    reset = rt.submit(ResetFault(rt.estop_seq))
    more(rt, 1)
    assert reset.ok and rt.mode == STOPPED and rt.latch_changed.is_set()
    rt.latch_changed.clear()
    rt.estop("again")
    more(rt, 1)
    assert rt.latch_changed.is_set()
    with pytest.raises(ValueError, match="mode"):
        rt.restore_latch(RUNNING, "x")


def test_start_after_a_reset_far_from_the_trajectory_approaches_with_bounded_speed() -> None:
    opts = RuntimeOptions(approach_speed_deg_s=20.0, approach_accel_deg_s2=40.0)
    rig = SimRig(seed=3)
    fc = FakeClock()
    rt = Runtime(make_loop(), rig, options=opts, clock=fc.clock, sleep=fc.sleep)
    col = Collector()
    stop = threading.Event()
    th = threading.Thread(target=rt.publisher, args=(col, stop, 0.001))
    th.start()
    try:
        rt.run(max_ticks=100)
        rt.estop("test")
        more(rt, 10)
        # While e-stopped the load is moved far away (by hand): 150 deg off the trajectory.
        rig.reset(position_deg=150.0)
        more(rt, 5)
        reset = rt.submit(ResetFault(rt.estop_seq))
        start = rt.submit(Start())
        more(rt, 12000)
    finally:
        stop.set()
        th.join(10.0)
    assert reset.ok and start.ok and rt.mode == RUNNING
    ref = col.column("ref_deg")
    cmd = col.column("command_deg_s")
    k0 = start.seq
    # The first reference after Start is where the rig was held (no jump), ...
    assert abs(ref[k0] - 150.0) < 0.1
    speeds = [(b - a) * 1000.0 for a, b in zip(ref[k0:], ref[k0 + 1 :], strict=False)]
    accels = [(b - a) * 1000.0 for a, b in itertools.pairwise(speeds)]
    # ... then it moves at no more than the bounds, ...
    assert max(abs(v) for v in speeds) <= 20.0 + 1e-6
    assert max(abs(a) for a in accels) <= 40.0 + 1e-3
    # ... and the speed command never saturates.
    limit = LoopConfig().command_limit_deg_s
    assert max(abs(u) for u in cmd[k0:]) < 0.9 * limit
    # ... and it ends on the trajectory (5 sin(0.5 t)), in 150/20 s plus braking.
    assert not rt.approaching
    assert abs(ref[-1]) <= 5.0 + 1e-9


def test_the_approach_allocates_nothing_that_stays() -> None:
    # The null rig never moves: the watchdog's tracking and saturation detectors would
    # (rightly) fault it; this test measures the approach's memory only.
    dead_rig_ok = WatchdogLimits(error_limit_deg=1e9, saturation_duration_s=1e9)
    rt = Runtime(make_loop(), NullRig(),
                 options=RuntimeOptions(ring_blocks=8, batch_size=20, watchdog=dead_rig_ok))
    rt.approach_from(1000.0)
    retained = retained_bytes(rt)
    assert rt.approaching  # still approaching during the measurement
    assert retained < 4096, retained


TICK_PROBE = """
import sys
import numba
from controller.core.config import LoopConfig
from controller.core.loop import LoopCoefficients, ServoLoop
from controller.process.runtime import Runtime
from controller.sim.rig_disturbances import rig_setup
from controller.sim.sim_rig import SimRig

def compiled():
    return sum(len(v.overloads) for m in list(sys.modules.values())
               if getattr(m, "__name__", "").startswith("controller")
               for v in vars(m).values() if isinstance(v, numba.core.registry.CPUDispatcher))

cfg = LoopConfig()
setup = rig_setup({names!r})
rig = SimRig(setup.params, rate_hz=cfg.rate_hz, disturbance=setup.torque)
rt = Runtime(ServoLoop(LoopCoefficients.build(cfg, 1)), rig)
new = LoopCoefficients.build(cfg.with_(q_type="q20", q_cutoff_hz=cfg.q_cutoff_hz * 1.5), 2)
imported = []
sys.addaudithook(lambda event, args: imported.append(args[0]) if event == "import" else None)
before = compiled()
rt.run(max_ticks=200)
rt.loop.request(new)  # an apply: prepared here, swapped in at a tick
rt._stop = False
rt.run(max_ticks=200)
print(rt.loop.active.version, compiled() - before, sorted(set(imported)))
"""


@pytest.mark.parametrize("names", [(), ("article-rig",)])
def test_the_ticks_import_and_compile_nothing(names: tuple[str, ...]) -> None:
    """In a fresh process (nothing compiled yet), the controller's ticks on the simulated rig,
    an apply's swap included, import no module and compile no numba kernel: all of it happens
    before the loop runs (the rig's step kernel was loaded on the first tick: 4.5 ms CPU,
    13-34 ms at load 22)."""
    code = TICK_PROBE.format(names=names)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300, check=True)
    assert out.stdout.strip().splitlines()[-1] == "2 0 []", out.stderr

"""A stand-in controller speaking the Zenoh contract (used when controller.process.node is absent).

Runs ServoLoop + SimRig in real time (1 kHz, batches every 20 ms), publishes StateBatch and
Status, answers ConfigRequest through the real gate (`controller.gate.analysis.analyse`) and
Command, and stops on any put to the e-stop key. Run: python fake_controller.py ENDPOINT RIG
"""

from __future__ import annotations

import json
import signal
import sys
import threading
import time

import zenoh

from controller import protocol as proto
from controller.core.config import LoopConfig
from controller.core.loop import LoopCoefficients, ServoLoop
from controller.core.trajectory import Trajectory
from controller.gate.analysis import analyse
from controller.sim.sim_rig import RigParams, SimRig


def main(endpoint: str, rig: str) -> int:
    try:
        from controller.zenoh_session import zenoh_config

        conf = zenoh_config(listen=(endpoint,))
    except ImportError:  # until controller/zenoh_session.py is committed
        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps("peer"))
        conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
        conf.insert_json5("scouting/multicast/enabled", "false")
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    cfg = LoopConfig()
    version = 1
    mode = "running"
    traj = Trajectory()
    loop = ServoLoop(LoopCoefficients.build(cfg, version))
    sim = SimRig(RigParams(), rate_hz=cfg.rate_hz, seed=0)
    lock = threading.Lock()
    with zenoh.open(conf) as s:
        pub_state = s.declare_publisher(proto.key_state(rig))
        pub_status = s.declare_publisher(proto.key_status(rig))
        q_cfg = s.declare_queryable(proto.key_config(rig))
        q_cmd = s.declare_queryable(proto.key_command(rig))
        estop_sub = s.declare_subscriber(proto.key_estop(rig), zenoh.handlers.RingChannel(8))
        seq = 0
        t_sim = 0.0
        t0 = time.monotonic()
        next_status = t0
        ts = cfg.period_s
        while not stop.is_set():
            # requests
            if estop_sub.try_recv() is not None:
                with lock:
                    mode = "estop"
            q = q_cfg.try_recv()
            if q is not None:
                req = proto.decode(q.payload.to_bytes(), proto.ConfigRequest)
                reasons: list[str] = []
                accepted = False
                if req.candidate is not None:
                    a = analyse(req.candidate)
                    if a.accepted:
                        with lock:
                            cfg = req.candidate
                            version += 1
                            loop.request(LoopCoefficients.build(cfg, version))
                        accepted = True
                    else:
                        reasons = list(a.reasons)
                reply = proto.ConfigReply(accepted=accepted, version=version, config=cfg,
                                          reasons=reasons)
                q.reply(proto.key_config(rig), proto.encode(reply))
                q.drop()
            q = q_cmd.try_recv()
            if q is not None:
                cmd = proto.decode(q.payload.to_bytes(), proto.Command)
                b = cmd.body
                with lock:
                    if isinstance(b, proto.EStop):
                        mode = "estop"
                    elif isinstance(b, proto.ResetFault) and mode == "estop":
                        mode = "stopped"
                    elif isinstance(b, proto.Start) and mode != "estop":
                        mode = "running"
                    elif isinstance(b, proto.Stop) and mode == "running":
                        mode = "stopped"
                    elif isinstance(b, proto.SetTrajectory):
                        traj = b.trajectory
                q.reply(proto.key_command(rig), proto.encode(
                    proto.CommandReply(ok=True, message="", mode=mode)))
                q.drop()
            # 20 ticks
            cols: dict[str, list[float]] = {k: [] for k in (
                "t_s", "ref_deg", "pos_deg", "speed_deg_s", "speed_ref_deg_s", "command_deg_s",
                "d_hat_deg_s", "error_deg")}
            for _ in range(20):
                r, rr = traj.at(t_sim)
                p, w = sim.read()
                u = loop.tick(r, rr, p, w) if mode == "running" else 0.0
                sim.step(u)
                for k, v in (("t_s", t_sim), ("ref_deg", r), ("pos_deg", p), ("speed_deg_s", w),
                             ("speed_ref_deg_s", loop.speed_ref_deg_s), ("command_deg_s", u),
                             ("d_hat_deg_s", loop.d_hat), ("error_deg", r - p)):
                    cols[k].append(v)
                t_sim += ts
            pub_state.put(proto.encode(proto.StateBatch(
                rig=rig, seq0=seq, rate_hz=cfg.rate_hz, config_version=version, **cols)))
            seq += 20
            now = time.monotonic()
            if now >= next_status:
                next_status = now + 0.2
                tm = proto.Timing(period_p50_us=1000, period_p99_us=1050, period_max_us=1200,
                                  compute_p50_us=30, compute_p99_us=60, compute_max_us=90,
                                  ticks=seq, overruns=0, skipped_ticks=0)
                pub_status.put(proto.encode(proto.Status(
                    rig=rig, plant="sim", mode=mode, t_s=t_sim, seq=seq - 1, trajectory=traj,
                    config_version=version, config=cfg, timing=tm, faults=[])))
            delay = t0 + t_sim - time.monotonic()
            if delay > 0:
                stop.wait(delay)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2]))

"""The controller process with a probe on its loop's per-tick compute times, for benchmarks.

Started by a bench as the controller (`start_controller(python_code=CODE, ...)`; pass
`--no-watch` yourself: with `python_code` the helper does not). The loop is the product's
(`python -m controller`), with a longer timing history (`HISTORY` ticks). One extra daemon
thread blocks on reading the FIFO named by $DOBTUNE_TICK_PROBE (no polling: it wakes only when
asked) and serves two requests, one line each:

- `mark`: remember the loop's tick count now;
- `dump PATH`: write the ticks since the mark to PATH (`.npy`, float64 rows: compute_us,
  period_us), then create PATH + ".done".

Only the bench asks, between windows; the probe never touches the tick.
"""

from __future__ import annotations

import os
import sys
import threading
from pathlib import Path

import numpy as np

HISTORY = 1 << 18
"""Ticks of history kept (262 s at 1 kHz): a window's ticks are all still there at its dump."""

CODE = (f"import sys; sys.path.insert(0, {str(Path(__file__).resolve().parent)!r}); "
        "import tick_probe; sys.exit(tick_probe.main())")


def _serve(fifo: str, holder: list) -> None:  # type: ignore[type-arg]
    mark = 0
    while True:
        with open(fifo) as f:  # blocks (GIL released) until the bench opens it
            for line in f:
                cmd, _, arg = line.strip().partition(" ")
                rt = holder[0] if holder else None
                if rt is None:
                    continue
                if cmd == "mark":
                    mark = rt._ti
                elif cmd == "dump":
                    end = rt._ti
                    cap = len(rt._compute_us)
                    idx = np.arange(max(mark, end - cap), end) % cap
                    out = np.stack([rt._compute_np[idx], rt._period_np[idx]])
                    np.save(arg, out)
                    Path(arg + ".done").touch()


def main() -> int:
    from dataclasses import replace

    import controller.__main__ as entry
    import controller.process.main as cmain
    from controller.process.runtime import Runtime, RuntimeOptions

    holder: list[Runtime] = []

    class ProbedRuntime(Runtime):
        def __init__(self, *args: object, options: RuntimeOptions | None = None,
                     **kwargs: object) -> None:
            opts = replace(options or RuntimeOptions(), timing_capacity=HISTORY)
            super().__init__(*args, options=opts, **kwargs)  # type: ignore[arg-type]
            holder.append(self)

    cmain.Runtime = ProbedRuntime  # type: ignore[misc]
    threading.Thread(target=_serve, args=(os.environ["DOBTUNE_TICK_PROBE"], holder),
                     name="tick-probe", daemon=True).start()
    return entry.main(sys.argv[1:])


# -- the bench's side ------------------------------------------------------------------------------


class Probe:
    """The bench's end of the FIFO: mark, then the compute times of the ticks since."""

    def __init__(self, fifo: Path, tmp: Path) -> None:
        self.fifo = fifo
        self.tmp = tmp
        self._k = 0

    def _send(self, line: str) -> None:
        with open(self.fifo, "w") as f:  # blocks until the controller's probe reads
            f.write(line + "\n")

    def mark(self) -> None:
        self._send("mark")

    def dump(self, timeout_s: float = 120.0) -> np.ndarray:
        """(compute_us, period_us) rows of every tick since the last mark, in order."""
        import time

        self._k += 1
        out = self.tmp / f"ticks{self._k}.npy"
        self._send(f"dump {out}")
        done = Path(str(out) + ".done")
        deadline = time.monotonic() + timeout_s
        while not done.exists():
            if time.monotonic() > deadline:
                raise TimeoutError(f"the controller's tick probe wrote no {out}")
            time.sleep(0.05)
        a = np.load(out)
        out.unlink()
        done.unlink()
        return a


#: Histogram bins for pooled quantiles: 0.01 us wide up to 1000 us (the last bin: beyond).
BIN_US = 0.01
TOP_US = 1000.0


def histogram(x: np.ndarray) -> np.ndarray:
    n = int(TOP_US / BIN_US)
    return np.bincount(np.minimum((x / BIN_US).astype(np.int64), n), minlength=n + 1)


def pooled_quantile(hists: np.ndarray, q: float) -> np.ndarray:
    """The q-quantile (inverted CDF, bin centres) of each row of pooled histograms."""
    cum = np.cumsum(hists, axis=-1)
    k = np.argmax(cum >= q * cum[..., -1:], axis=-1)
    return (k + 0.5) * BIN_US


def block_bootstrap(with_h: np.ndarray, without_h: np.ndarray, q: float,
                    rng: np.random.Generator, n_boot: int = 4000
                    ) -> tuple[float, float, float, float, float]:
    """The pooled q-quantile of each arm over all blocks, their difference (with minus
    without), and the difference's 95 % percentile interval from resampling whole blocks with
    replacement (a block: its windows with and without, taken together, so the dependence
    between windows near in time stays inside a block). with_h, without_h: (blocks, bins)
    histograms of each block's ticks per arm. Returns (with, without, diff, lo, hi)."""
    nb = with_h.shape[0]
    arms = []
    for h in (with_h, without_h):
        cum = np.cumsum(h, axis=1).astype(np.float64)  # per block; pooling is linear
        arms.append(cum)
    w = float(pooled_quantile(with_h.sum(0), q))
    wo = float(pooled_quantile(without_h.sum(0), q))
    counts = np.stack([np.bincount(rng.integers(0, nb, nb), minlength=nb)
                       for _ in range(n_boot)]).astype(np.float64)
    est = []
    for cum in arms:
        # Only the bins where a resample's quantile can fall (checked below), for speed.
        pooled = cum.sum(0)
        lo_k = int(np.searchsorted(pooled, max(0.0, q - 0.2) * pooled[-1]))
        hi_k = int(np.searchsorted(pooled, min(1.0, q + 0.8 * (1 - q)) * pooled[-1])) + 1
        part = counts @ cum[:, lo_k:hi_k]
        total = counts @ cum[:, -1]
        hit = part >= q * total[:, None]
        if not hit[:, -1].all() or (lo_k > 0 and hit[:, 0].any()):
            part, lo_k = counts @ cum, 0  # a resample outside the range: all bins
            hit = part >= q * total[:, None]
        est.append((np.argmax(hit, axis=1) + lo_k + 0.5) * BIN_US)
    d = est[0] - est[1]
    lo, hi = np.percentile(d, [2.5, 97.5])
    return w, wo, w - wo, float(lo), float(hi)

"""The runtime's sample ring (`controller.process.runtime`): blocks of column buffers that the
loop fills tick by tick (`Runtime._store`, preallocated: no allocation on the tick) and the
publisher thread hands on, block by block, in order (`SampleRing.drain`).

Only the loop writes `produced` and the block it fills; only the publisher writes `consumed`.
Block i is free for the loop while produced - consumed < blocks.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence

__all__ = ["BatchSink", "SampleRing"]

BatchSink = Callable[[int, int, str, Sequence[list[float]]], None]
"""sink(seq0, config_version, mode, columns): columns are lists of equal length, owned by the
caller (copies)."""


class SampleRing:
    """Blocks of column buffers shared by the loop (producer) and the publisher (consumer);
    `mode`: every block's mode until the loop first fills it."""

    def __init__(self, batch: int, blocks: int, ncols: int, mode: str) -> None:
        self.batch = batch
        self.blocks = blocks
        self.cols = [[[0.0] * batch for _ in range(ncols)] for _ in range(blocks)]
        self.seq0 = [0] * blocks
        self.n = [0] * blocks
        self.version = [0] * blocks
        self.mode = [mode] * blocks
        self.produced = 0
        self.consumed = 0
        self.ready = threading.Event()

    def drain(self, sink: BatchSink) -> None:
        """(The publisher's thread.) Hand every finished block to `sink`, in order; a block
        counts as consumed even when `sink` raises (the raise goes on)."""
        while self.consumed < self.produced:
            i = self.consumed % self.blocks
            n = self.n[i]
            cols = [c[:n] for c in self.cols[i]]
            try:
                sink(self.seq0[i], self.version[i], self.mode[i], cols)
            finally:
                self.consumed += 1

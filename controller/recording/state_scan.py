"""The /state messages of a recording read straight into columns (numba), for `read_recording`.

A 10-minute recording has 600 000 /state messages. Taking each as a Python object (the record
walk, one bytes object per message, a msgspec Struct per message, a Python list per column) took
about 2 s idle and 18 s at load 15. Here a compiled scan walks the decompressed records of a
chunk, checks that each /state message is exactly what `Recorder.state` writes (the keys in
that order, numbers, `null` only for a non-finite sample, the mode a plain string) and copies
the number tokens into one JSON array per chunk, which msgspec decodes as floats in one call.
Anything else (another key order, extra keys, a string with escapes) stops the scan with
`SHAPE_MISMATCH`: the caller then reads the file with its general decoder, which gives the
same arrays (tests/test_mcap_io.py checks both on the same files).
"""

from __future__ import annotations

from concurrent.futures import Executor, Future
from typing import Any

import msgspec
import numpy as np

from controller.core.numba_start import numba
from controller.core.samples import STATE_COLUMNS

#: The keys of a /state message in `Recorder.state`'s order; all but the last are numbers.
KEYS = ("seq", *STATE_COLUMNS, "config_version", "mode")
N_NUMBERS = len(KEYS) - 1
_INT_FIELDS = (0, N_NUMBERS - 1)  # seq, config_version: integers, never null

OK, SHAPE_MISMATCH, TRUNCATED = 0, 1, 2
OP_MESSAGE = 0x05


def _patterns() -> tuple[np.ndarray, np.ndarray]:
    """`{"seq":`, `,"t_s":`, ... as one byte array and the offsets of each."""
    parts = [(b"{" if i == 0 else b",") + b'"' + k.encode() + b'":' for i, k in enumerate(KEYS)]
    offsets = np.cumsum([0] + [len(p) for p in parts]).astype(np.int64)
    return np.frombuffer(b"".join(parts), dtype=np.uint8).copy(), offsets


PATTERNS, PATTERN_OFFSETS = _patterns()


@numba.njit(cache=True, nogil=True)
def _u64(data: np.ndarray, at: int) -> int:
    v = 0
    for i in range(7, -1, -1):
        v = (v << 8) | int(data[at + i])
    return v


@numba.njit(cache=True, nogil=True)
def _is_number_byte(c: int, integer: bool) -> bool:
    if 48 <= c <= 57 or c == 45:  # 0-9 and '-'
        return True
    return not integer and (c == 46 or c == 43 or c == 101 or c == 69)  # . + e E


@numba.njit(cache=True, nogil=True)
def scan(data: np.ndarray, at: int, end: int, state_channel: int, pats: np.ndarray,
         pat_off: np.ndarray, txt: np.ndarray, times: np.ndarray, runs: np.ndarray,
         cur: np.ndarray) -> int:
    """Consume the /state message records of `data[at:end]` from `at` on; return where it
    stopped: `end`, or the first record that is not a /state message (for the caller), or a
    bad one (cur[3] = SHAPE_MISMATCH or TRUNCATED).

    cur: [0] bytes written to `txt` (numbers, each followed by ','), [1] messages taken (their
    log times in `times`), [2] mode runs (`runs[i]` = first message, start, length of the mode
    string in `data`), [3] status, [4]/[5] the previous message's mode (start, length; -1: none).
    """
    n_keys = pat_off.shape[0] - 1
    n_num = n_keys - 1
    while at < end:
        if at + 9 > end:
            cur[3] = TRUNCATED
            return at
        op = int(data[at])
        body = at + 9
        nxt = body + _u64(data, at + 1)
        if nxt > end or nxt < body:
            cur[3] = TRUNCATED
            return at
        if op != OP_MESSAGE or nxt - body < 22:
            return at
        cid = int(data[body]) | (int(data[body + 1]) << 8)
        if cid != state_channel:
            return at
        p = body + 22
        w = cur[0]
        ms, ml = -1, 0
        for k in range(n_keys):
            a, b = pat_off[k], pat_off[k + 1]
            if p + (b - a) > nxt:
                cur[3] = SHAPE_MISMATCH
                return at
            for i in range(b - a):
                if data[p + i] != pats[a + i]:
                    cur[3] = SHAPE_MISMATCH
                    return at
            p += b - a
            if k < n_num:
                integer = k == 0 or k == n_num - 1
                s = p
                while p < nxt and data[p] != 44 and data[p] != 125:  # ',' '}'
                    p += 1
                n = p - s
                if (n == 4 and not integer and data[s] == 110 and data[s + 1] == 117
                        and data[s + 2] == 108 and data[s + 3] == 108):  # null
                    pass
                else:
                    if n == 0:
                        cur[3] = SHAPE_MISMATCH
                        return at
                    for i in range(s, p):
                        if not _is_number_byte(int(data[i]), integer):
                            cur[3] = SHAPE_MISMATCH
                            return at
                for i in range(n):
                    txt[w + i] = data[s + i]
                w += n
                txt[w] = 44
                w += 1
            else:  # the mode: a string without escapes
                if p >= nxt or data[p] != 34:
                    cur[3] = SHAPE_MISMATCH
                    return at
                p += 1
                ms = p
                while p < nxt and data[p] != 34:
                    if data[p] == 92 or data[p] < 32:  # backslash, control character
                        cur[3] = SHAPE_MISMATCH
                        return at
                    p += 1
                if p >= nxt:
                    cur[3] = SHAPE_MISMATCH
                    return at
                ml = p - ms
                p += 1
        if p + 1 != nxt or data[p] != 125:  # '}' and nothing after it
            cur[3] = SHAPE_MISMATCH
            return at
        j = cur[1]
        times[j] = _u64(data, body + 6)
        same = cur[5] == ml and cur[4] >= 0
        if same:
            for i in range(ml):
                if data[cur[4] + i] != data[ms + i]:
                    same = False
                    break
        if not same:
            r = cur[2]
            runs[r, 0], runs[r, 1], runs[r, 2] = j, ms, ml
            cur[2] = r + 1
        cur[4], cur[5] = ms, ml
        cur[0] = w
        cur[1] = j + 1
        at = nxt
    return at


_floats = msgspec.json.Decoder(list[float | None])


def _numbers(txt: np.ndarray, n: int) -> np.ndarray:
    """The JSON array of numbers in `txt` as an (n, N_NUMBERS) float64 array."""
    values = np.array(_floats.decode(txt.data), dtype=np.float64)
    if values.size != n * N_NUMBERS:
        raise ValueError(f"/state: {values.size} numbers for {n} messages")
    return values.reshape(n, N_NUMBERS)


class StateColumns:
    """Accumulates the /state messages chunk by chunk: numbers, log times and modes. The
    scan runs without the GIL; the numbers of each chunk are decoded on `pool` (when given)
    while the caller scans the next one."""

    def __init__(self, pool: Executor | None = None) -> None:
        self._pool = pool
        self._numbers: list[Future[np.ndarray] | np.ndarray] = []
        self._times: list[np.ndarray] = []
        self._modes: list[str] = []
        self._mode_starts: list[int] = []
        self.n = 0

    def take(self, data: np.ndarray, at: int, end: int, state_channel: int) -> tuple[int, int]:
        """Scan `data[at:end]`; returns (where it stopped, status)."""
        size = end - at
        txt = np.empty(size + 2, dtype=np.uint8)
        txt[0] = 91  # '['
        times = np.empty(size // 31 + 1, dtype=np.int64)
        runs = np.empty((size // 31 + 1, 3), dtype=np.int64)
        cur = np.array([1, 0, 0, 0, -1, 0], dtype=np.int64)
        stop = scan(data, at, end, state_channel, PATTERNS, PATTERN_OFFSETS, txt, times, runs,
                    cur)
        n = int(cur[1])
        if n:
            txt[cur[0] - 1] = 93  # the last ',' becomes ']'
            txt = txt[: cur[0]]
            self._numbers.append(_numbers(txt, n) if self._pool is None
                                 else self._pool.submit(_numbers, txt, n))
            self._times.append(times[:n].copy())
            for first, start, length in runs[: cur[2]]:
                self._mode_starts.append(self.n + int(first))
                self._modes.append(bytes(data[start : start + length]).decode())
            self.n += n
        return stop, int(cur[3])

    def columns(self) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """Unsorted columns (seq and config_version as float64, as the general decoder's) and
        the log times in ns."""
        parts = [x.result() if isinstance(x, Future) else x for x in self._numbers]
        num = np.concatenate(parts) if parts else np.empty((0, N_NUMBERS), dtype=np.float64)
        by_column = np.ascontiguousarray(num.T)  # one contiguous row per column
        cols: dict[str, Any] = {k: by_column[i] for i, k in enumerate(KEYS[:-1])}
        counts = np.diff(np.asarray([*self._mode_starts, self.n], dtype=np.int64)).astype(np.int64)
        cols["mode"] = np.repeat(np.array(self._modes, dtype=object), counts)
        times = np.concatenate(self._times) if self._times else np.empty(0, dtype=np.int64)
        return cols, times

"""The audit tamper table: every kind of tampering with `<state-dir>/audit.jsonl` tried on a
fresh log, and whether `dobtune audit verify` catches it (exit code 1) by the chain alone and
against an anchor (a record hash published earlier, e.g. Status.audit_head). Prints a table;
not a test (tests/test_audit.py asserts each case).

    PYTHONPATH=$PWD .venv/bin/python tests/bench/audit_tamper_table.py
"""

from __future__ import annotations

import io
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from test_audit import ALTERATIONS, _rehash, lines_of, make_log, sha

from controller.cli.audit import verify_main
from controller.process.audit import AuditLog, verify


def _exit(d: Path, anchor: str | None = None, accept: bool = False) -> int:
    return verify_main(d, anchor, False, io.StringIO(), accept)


def _restart(d: Path) -> None:
    AuditLog(d / "audit.jsonl", rig="bench").close()


def _rewrite_chain(ls: list[bytes]) -> list[bytes]:
    prev = sha(ls[2].rstrip(b"\n"))
    out = list(ls)
    for i in range(3, len(ls)):
        out[i] = _rehash(ls[i], prev=prev, **({"user": "mallory"} if i == 3 else {}))
        prev = sha(out[i].rstrip(b"\n"))
    return out


# name: (alteration of the lines, restart the controller after it?)
EXTRA: dict[str, tuple[Callable[[list[bytes]], list[bytes]], bool]] = {
    "last record erased to a torn tail": (lambda ls: [*ls[:-1], ls[-1][:40]], False),
    "... then the controller restarted (acknowledges)": (lambda ls: [*ls[:-1], ls[-1][:40]],
                                                         True),
    "last line deleted (at a line boundary)": (lambda ls: ls[:-1], False),
    "last record edited and rehashed": (lambda ls: [*ls[:-1], _rehash(ls[-1], user="mallory")],
                                        False),
    "whole tail rewritten and rehashed": (_rewrite_chain, False),
    "log emptied": (lambda ls: [], False),
    "complete garbage line appended, restarted (set aside)": (lambda ls: [*ls, b"x\n"], True),
}


def main() -> None:
    rows: list[tuple[str, str, str, str]] = []
    cases: list[tuple[str, Callable[[list[bytes]], list[bytes]], bool]] = [
        (name, alter, False) for name, (alter, _, _) in sorted(ALTERATIONS.items())
    ] + [(name, alter, restart) for name, (alter, restart) in EXTRA.items()]
    for name, alter, restart in cases:
        with tempfile.TemporaryDirectory() as tmp:
            d = Path(tmp)
            path = make_log(d)
            anchor = verify(path).head
            path.write_bytes(b"".join(alter(lines_of(path))))
            if restart:
                _restart(d)
            alone, anchored = _exit(d), _exit(d, anchor)
            accepted = _exit(d, anchor=None, accept=True)
            rows.append((name, "caught" if alone == 1 else f"NOT caught ({alone})",
                         "caught" if anchored == 1 else f"NOT caught ({anchored})",
                         "caught" if accepted == 1 else f"accepted ({accepted})"))
    w = max(len(r[0]) for r in rows)
    print(f"{'tampering':<{w}}  {'chain alone':<16} {'with anchor':<16} "
          "--accept-torn-tail (no anchor)")
    for r in rows:
        print(f"{r[0]:<{w}}  {r[1]:<16} {r[2]:<16} {r[3]}")
    n = len(rows)
    print(f"\n{sum(r[1] == 'caught' for r in rows)}/{n} caught by the chain alone, "
          f"{sum(r[2] == 'caught' for r in rows)}/{n} against an anchor")


if __name__ == "__main__":
    main()

"""`dobtune audit show|verify DIR`: read and check a controller's audit log (command body).

DIR is the controller's state directory (the log is `DIR/audit.jsonl`) or the log file itself.
`verify` exit codes: 0 the chain is intact, 1 it is not (an edited, deleted, inserted or moved
line, a truncated hash, a missing anchor, a torn line, or a damaged log the controller set
aside next to it), 2 bad input (no such log, unreadable, an anchor of neither form). A torn
line (a crash while writing, or the last record erased) fails the check even when the
controller acknowledged it on restart, unless `--accept-torn-tail` is given: it then lists
what it accepted.
`show` exits 0, or 2 on bad input.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import deque
from pathlib import Path
from typing import Any, TextIO

from controller.process.audit import (
    AUDIT_FILE,
    CORE_KEYS,
    VerifyResult,
    iter_lines,
    parse_anchor,
    parse_record,
    verify,
)

__all__ = ["show_main", "verify_main"]

EXIT_OK, EXIT_ALTERED, EXIT_BAD_INPUT = 0, 1, 2


def log_file(target: Path) -> Path:
    """The audit log named by a state directory or a file."""
    return target / AUDIT_FILE if target.is_dir() else target


def _bad_input(msg: str, out: TextIO, as_json: bool) -> int:
    out.write(json.dumps({"error": msg}) + "\n" if as_json else f"error: {msg}\n")
    return EXIT_BAD_INPUT


def _missing(path: Path, out: TextIO, as_json: bool) -> int:
    what = "no audit log" if not path.exists() else "not a file"
    return _bad_input(f"{path}: {what}", out, as_json)


def _versions(rec: dict[str, Any]) -> str:
    before, after = rec["version_before"], rec["version_after"]
    if before is None and after is None:
        return "-"
    return f"v{before}" if after == before else f"v{before}->v{after}"


def format_record(rec: dict[str, Any]) -> str:
    """One readable line: seq, time, user, action, outcome, versions, the other fields."""
    extra = " ".join(
        f"{k}={json.dumps(rec[k], separators=(',', ':'))}"
        for k in sorted(rec)
        if k not in CORE_KEYS
    )
    return (
        f"{rec['seq']:>6} {rec['time']} {rec['user'] or '-':<12} {rec['action']:<16} "
        f"{rec['outcome']:<8} {_versions(rec):<9} {extra}"
    ).rstrip()


def show_main(target: Path, as_json: bool, tail: int | None, out: TextIO) -> int:
    """Print the log's records, oldest first (the last `tail` lines only if given). Lines that
    are not self-consistent records are shown as damaged; `verify` checks the chain."""
    path = log_file(target)
    if not path.is_file():
        return _missing(path, out, as_json)
    try:
        lines: deque[tuple[int, bytes]] = deque(maxlen=tail)
        for n, line, _ in iter_lines(path):
            lines.append((n, line))
    except OSError as exc:
        return _bad_input(f"{path}: cannot read: {exc.strerror or exc}", out, as_json)
    for n, line in lines:
        rec, why = parse_record(line)
        if as_json:
            item = rec if rec is not None else {"line": n, "damaged": why}
            out.write(json.dumps(item, separators=(",", ":")) + "\n")
        elif rec is not None:
            out.write(format_record(rec) + "\n")
        else:
            out.write(f"{'?':>6} line {n}: damaged: {why}\n")
    return EXIT_OK


def _set_aside(path: Path) -> list[str]:
    """Damaged logs the controller set aside next to this one (not verified here)."""
    return sorted(p.name for p in path.parent.glob("audit.damaged-*.jsonl"))


def _report_text(path: Path, r: VerifyResult, kept: list[str]) -> str:
    if r.ok:
        lines = [f"{path}: chain intact, {r.records} records, head {r.head}"]
    elif r.bad_line is not None:
        lines = [
            f"{path}: line {r.bad_line}: {r.reason}",
            f"  {r.records} records verified before it",
        ]
    else:
        lines = [f"{path}: {r.reason}", f"  {r.records} records verified, head {r.head}"]
    lines += [f"  note: {d}" for d in r.damaged if d not in r.accepted_torn]
    lines += [f"  ACCEPTED torn tail (--accept-torn-tail): {d}" for d in r.accepted_torn]
    lines += [f"  ACCEPTED lost records (--accept-lost): {d}" for d in r.accepted_lost]
    lines += [f"  NOT INTACT: {name} is a damaged log the controller set aside (inspect it, then "
              "archive it elsewhere)" for name in kept]
    return "\n".join(lines) + "\n"


def verify_main(
    target: Path, anchor: str | None, as_json: bool, out: TextIO, accept_torn_tail: bool = False,
    accept_lost: bool = False,
) -> int:
    """Check the chain; print the verdict. Returns the exit code. A torn line fails the check
    unless `accept_torn_tail`, a log that continues a lost one unless `accept_lost` (then it
    is printed as accepted)."""
    path = log_file(target)
    if anchor is not None:
        try:
            parse_anchor(anchor)
        except ValueError as exc:
            return _bad_input(str(exc), out, as_json)
    if not path.is_file():
        return _missing(path, out, as_json)
    try:
        result = verify(path, anchor=anchor, accept_torn_tail=accept_torn_tail,
                        accept_lost=accept_lost)
    except OSError as exc:
        return _bad_input(f"{path}: cannot read: {exc.strerror or exc}", out, as_json)
    kept = _set_aside(path)
    ok = result.ok and not kept
    if as_json:
        doc = {
            "ok": ok,
            "records": result.records,
            "bad_line": result.bad_line,
            "reason": result.reason,
            "head": result.head,
            "notes": list(result.damaged),
            "accepted_torn": list(result.accepted_torn),
            "accepted_lost": list(result.accepted_lost),
            "set_aside": kept,
        }
        out.write(json.dumps(doc) + "\n")
    else:
        out.write(_report_text(path, result, kept))
    return EXIT_OK if ok else EXIT_ALTERED


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="audit_command", required=True)
    show = sub.add_parser("show", help="print the records", description="print the records")
    show.add_argument("dir", type=Path, metavar="DIR", help="state directory (or audit.jsonl)")
    show.add_argument("--json", action="store_true", help="one JSON object per record")
    show.add_argument("--tail", type=_positive_int, default=None, metavar="N",
                      help="only the last N lines")
    check = sub.add_parser(
        "verify", help="check the hash chain", description="check the hash chain (exit 0 "
        "intact, 1 altered, 2 bad input)"
    )
    check.add_argument("dir", type=Path, metavar="DIR", help="state directory (or audit.jsonl)")
    check.add_argument("--anchor", default=None, metavar="SEQ:HASH",
                       help="a record known from elsewhere that must be in the chain: "
                       "<seq>:<sha256> as Status.audit_head gives it, or a bare record hash")
    check.add_argument("--json", action="store_true")
    check.add_argument("--accept-torn-tail", action="store_true",
                       help="accept torn lines (a crash while writing; also what erasing the "
                       "last record leaves): listed as accepted instead of failing the check")
    check.add_argument("--accept-lost", action="store_true",
                       help="accept a log that continues a lost one (deleted, truncated or "
                       "replaced; its first record is audit.continued): listed as accepted")


def _positive_int(value: str) -> int:
    try:
        n = int(value)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value!r}")
    return n


def run(args: argparse.Namespace) -> int:
    if args.audit_command == "show":
        return show_main(args.dir, args.json, args.tail, sys.stdout)
    return verify_main(args.dir, args.anchor, args.json, sys.stdout, args.accept_torn_tail,
                       args.accept_lost)


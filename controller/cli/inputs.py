"""Reading the files a command is given: a configuration, plant knowledge; `BadInput` names
the file and the line or field."""

from __future__ import annotations

import json
from pathlib import Path

import msgspec

from controller.core.config import LoopConfig, config_from_builtins
from controller.core.errors import ConfigError
from controller.gate.knowledge import COMMISSIONING_BOUND, KnowledgeRecord, PlantKnowledge

__all__ = ["BadInput", "load_config", "load_knowledge"]


def load_knowledge(path: Path | None) -> PlantKnowledge:
    """The plant knowledge in `path` (a KnowledgeRecord as JSON), or the simulated rig's model
    with the commissioning bound. Raises BadInput naming the file and the field."""
    if path is None:
        return PlantKnowledge(bound=COMMISSIONING_BOUND, source="simulated rig model")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise BadInput(f"{path}: cannot read plant knowledge: {exc}") from exc
    try:
        rec = msgspec.json.decode(data, type=KnowledgeRecord)
        return rec.to_knowledge()
    except msgspec.ValidationError as exc:
        raise BadInput(f"{path}: plant knowledge: {exc}") from exc
    except (msgspec.DecodeError, ValueError) as exc:
        raise BadInput(f"{path}: plant knowledge: {exc}") from exc


class BadInput(Exception):
    pass


def _field_line(text: str, field: str) -> int | None:
    """Line (1-based) where the top-level key of `field` ("nominal.mn_den[2]") appears."""
    key = field.split(".", 1)[0].split("[", 1)[0]
    needle = f'"{key}"'
    for i, line in enumerate(text.splitlines(), start=1):
        if needle in line:
            return i
    return None


def load_config(path: Path | None) -> LoopConfig:
    if path is None:
        return LoopConfig()
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise BadInput(f"{path}: cannot read config: {exc}") from exc
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise BadInput(f"{path}:{exc.lineno}: invalid JSON: {exc.msg}") from exc
    try:
        return config_from_builtins(data)
    except ConfigError as exc:
        line = _field_line(text, exc.field)
        where = f"{path}:{line}" if line is not None else str(path)
        raise BadInput(f"{where}: field {exc.field!r}: {exc}") from exc

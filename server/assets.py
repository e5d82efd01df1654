"""The dashboard's web assets (`web_assets/`: page script, header, help texts), found through
the import system: in the source tree and in an installed wheel alike (package data)."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

__all__ = ["web_asset"]


def web_asset(name: str) -> Path:
    """The path of `web_assets/<name>` (it may not exist: the caller reads it and says so)."""
    return Path(str(resources.files("web_assets").joinpath(name)))

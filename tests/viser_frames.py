"""What a viser websocket frame carries, for tests and benches that count messages."""

from __future__ import annotations

__all__ = ["message_types"]


def message_types(frame: bytes) -> list[str]:
    """The viser message types in one websocket frame: viser's hybrid wire format (8-byte
    decompressed size, 8-byte compressed size, zstd-compressed msgpack {"messages": [...]},
    then the raw binary buffers); a GUI update is named with the properties it sets
    ("GuiUpdateMessage:data"). ["?"] for a frame that does not decode."""
    import msgspec
    import zstandard

    try:
        size = int.from_bytes(frame[:8], "little")
        packed = int.from_bytes(frame[8:16], "little")
        raw = zstandard.ZstdDecompressor().decompress(frame[16:16 + packed],
                                                      max_output_size=size)
        obj = msgspec.msgpack.decode(raw)
    except (msgspec.DecodeError, zstandard.ZstdError, ValueError):
        return ["?"]
    out: list[str] = []
    for m in obj.get("messages", []) if isinstance(obj, dict) else []:
        kind = str(m.get("type", "?")) if isinstance(m, dict) else "?"
        if kind == "GuiUpdateMessage" and isinstance(m.get("updates"), dict):
            kind += ":" + ",".join(sorted(m["updates"]))
        out.append(kind)
    return out or ["?"]

"""Class names of palette colors (labels.json: ``[{color: [r, g, b], class_name, ...}, ...]``) and the
parsing of object ids written by people (``#ff7700``, ``0xff7700``, ``ff7700``, ``16742144``)."""

from __future__ import annotations

import json
import os
import re
from collections.abc import Iterable, Mapping
from pathlib import Path

_HEX = re.compile(r"^(?:#|0x)?([0-9a-fA-F]{6})$")


def parse_object_id(value: str | int) -> int:
    """A packed palette color from ``#rrggbb``, ``0xrrggbb``, ``rrggbb`` or a decimal integer.

    Six hex digits always read as a color (``"102030"`` is 0x102030), so decimals need another length."""
    if isinstance(value, bool):
        raise ValueError(f"not an object id: {value!r}")
    if isinstance(value, int):
        oid = value
    else:
        text = str(value).strip()
        match = _HEX.match(text)
        if match:
            oid = int(match.group(1), 16)
        elif text.isdigit():
            oid = int(text)
        else:
            raise ValueError(f"not an object id (expected #rrggbb, 0xrrggbb or an integer): {value!r}")
    if not 0 <= oid <= 0xFFFFFF:
        raise ValueError(f"object id {value!r} is not a 24-bit palette color")
    return oid


def format_object_id(oid: int) -> str:
    return f"#{int(oid):06x}"


def labels_from_entries(entries: Iterable[Mapping]) -> dict[int, str]:
    """``{object id: class name}`` from labels.json-style entries (a sequence's ``labels()``)."""
    out: dict[int, str] = {}
    for n, entry in enumerate(entries):
        try:
            r, g, b = (int(c) for c in entry["color"])
            name = str(entry["class_name"]).strip()
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"labels entry {n}: expected color [r, g, b] and class_name ({exc})") from None
        if not all(0 <= c <= 255 for c in (r, g, b)):
            raise ValueError(f"labels entry {n}: color {[r, g, b]} outside 0..255")
        if name:
            out[(r << 16) | (g << 8) | b] = name
    return out


def load_labels(path: str | os.PathLike) -> dict[int, str]:
    """Labels from a labels.json file (Replica / plain-layout format)."""
    path = Path(path)
    try:
        entries = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: unreadable labels file ({exc})") from None
    if not isinstance(entries, list):
        raise ValueError(f"{path}: expected a JSON list of {{color, class_name}} entries")
    return labels_from_entries(entries)


def noun(label: str) -> str:
    """A class name as a noun phrase for descriptions: "indoor-plant" -> "indoor plant"."""
    return " ".join(re.sub(r"[-_]+", " ", label).split())

"""Class names as words: the noun phrase of a labels.json class name (ids and labels.json: core.evidence.palette)."""

from __future__ import annotations

import re


def noun(label: str) -> str:
    """A class name as a noun phrase for descriptions: "indoor-plant" -> "indoor plant"."""
    return " ".join(re.sub(r"[-_]+", " ", label).split())

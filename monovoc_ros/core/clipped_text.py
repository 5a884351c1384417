"""Text from an input, bounded before it is reported: an error, a log line or a refusal may quote a hostile message
(a 300 kB field name, a 1 MB image encoding)."""

from __future__ import annotations


def clipped(text: str, limit: int) -> str:
    """`text`, or its first `limit` characters and how many more there were."""
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text) - limit} characters more)"

"""Class names as words: the noun phrase of a labels.json class name (ids and labels.json: core.evidence.palette),
and the head noun that a text and a label are matched by."""

from __future__ import annotations

import re

# Words that open an English noun phrase's post-modifier ("a box of tissues", "the board on wheels", "the cup
# next to the sink"): the head noun comes before them.
_POST_MODIFIERS = frozenset(
    "of on in with near under above below behind beside between by at from to inside onto for next "
    "without along across against over beneath atop underneath that which".split()
)
# Words that open one only when "of" / "to" follows ("the chair left of the table", "the cup closest to me").
_BEFORE_OF = frozenset("left right front closest nearest farthest furthest".split())


def noun(label: str) -> str:
    """A class name as a noun phrase for descriptions: "indoor-plant" -> "indoor plant"."""
    return " ".join(re.sub(r"[-_]+", " ", label).split())


def _singular(word: str) -> str:
    if word.endswith("ies") and len(word) > 4:
        return word[:-3] + "y"
    if word.endswith(("ches", "shes", "sses", "xes")):
        return word[:-2]
    if word.endswith("s") and not word.endswith(("ss", "us", "is")) and len(word) > 2:
        return word[:-1]
    return word


def head_noun(phrase: str) -> str:
    """The head noun of a noun phrase, singular: its last word before any post-modifier ("the dark blue chairs"
    -> "chair", "a box of tissues" -> "box", "the board on wheels" -> "board"; "" for none)."""
    words = re.sub(r"[?.!,;:]", " ", phrase.lower()).split()
    for n, word in enumerate(words):
        follows = words[n + 1] if n + 1 < len(words) else ""
        if n > 0 and (word in _POST_MODIFIERS or (word in _BEFORE_OF and follows in ("of", "to"))):
            words = words[:n]
            break
    # A hyphenated class name ("indoor-plant", "tv-screen") ends in its head; "built-in" stays one word above.
    last = re.sub(r"[-_]+", " ", words[-1]).split() if words else []
    return _singular(last[-1]) if last else ""

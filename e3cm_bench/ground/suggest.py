"""'Did you mean ...?' for a mistyped name: the closest of the names a choice takes."""

from __future__ import annotations

import difflib
from collections.abc import Iterable


def did_you_mean(word: object, choices: Iterable[str]) -> str:
    """' (did you mean 'sift'?)' for the closest choices (at most 3), or '' when none is close
    (difflib's ratio of at least 0.6: one or two letters off in a short name)."""
    if not isinstance(word, str):
        return ""
    close = difflib.get_close_matches(word, [str(c) for c in choices], n=3, cutoff=0.6)
    if not close:
        return ""
    return " (did you mean " + " or ".join(repr(c) for c in close) + "?)"

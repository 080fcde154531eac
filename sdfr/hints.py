"""Did-you-mean hints for a mistyped word: one helper for every file reader and command line.

Imports nothing at load (the daemon's config reader uses it, and the daemon pays for every
module it loads): difflib is imported only when a mistake is being explained.
"""

from __future__ import annotations

from collections.abc import Iterable

CUTOFF = 0.6  # difflib's ratio below which a word is not offered as a correction


def closest(word: str, choices: Iterable[str]) -> str | None:
    """The choice spelled most like `word`, or None when none is close."""
    import difflib

    found = difflib.get_close_matches(word, list(choices), n=1, cutoff=CUTOFF)
    return found[0] if found else None


def did_you_mean(word: str, choices: Iterable[str]) -> str:
    """`` (did you mean 'x'?)`` for the closest of `choices`, or nothing."""
    close = closest(word, choices)
    return f" (did you mean {close!r}?)" if close is not None else ""

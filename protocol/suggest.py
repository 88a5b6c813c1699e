"""Did-you-mean for names a user types (circuits, brains, noise models, variations, matrix keys): standard library only.

>>> did_you_mean("simpel", ["simple", "monaco"])
"; did you mean 'simple'?"
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable

CLOSE_ENOUGH = 0.6  # difflib's ratio: 'simpel' -> 'simple' is 0.83, 'montmelo' -> 'montreal' 0.62, 'xyz' -> '' below


def did_you_mean(word: object, choices: Iterable[str]) -> str:
    """``"; did you mean 'x'?"`` for the closest of ``choices`` to ``word``, or ``""`` when none is close."""
    if not isinstance(word, str):
        return ""
    close = difflib.get_close_matches(word, list(choices), n=1, cutoff=CLOSE_ENOUGH)
    return f"; did you mean {close[0]!r}?" if close else ""

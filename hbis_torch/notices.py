"""The lines a step says about its work, and which of them ask the user to act.

Library functions that take a ``messages`` list append plain strings to it: what they did and
found (frames down-weighted, the figures of an adaptation, a model tier switched). A line that
asks the user to do something (pass a flag, capture the burst again, distrust a result) is a
:class:`UserAction` instead, a ``str`` that says so. The command line shows the plain lines
only with ``-v`` and the others by default, marked ``warning:``; ``-q`` shows neither
(docs/design.md, the CLI contract).
"""

from __future__ import annotations


class UserAction(str):
    """A message that asks the user to act (a ``str`` in every other respect).

    Examples
    --------
    >>> line = act("pass --bit-depth 12")
    >>> line, asks_to_act(line), asks_to_act("frame 3 down-weighted")
    ('pass --bit-depth 12', True, False)
    """

    __slots__ = ()


def act(text: str) -> UserAction:
    """``text`` marked as a line that asks the user to act."""
    return UserAction(text)


def asks_to_act(message) -> bool:
    """Whether ``message`` asks the user to act (was made by :func:`act`)."""
    return isinstance(message, UserAction)

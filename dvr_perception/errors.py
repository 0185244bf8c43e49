"""Exceptions and warnings raised by dvr_perception.

Every user-facing error is a :class:`DVRInputError` (a ``ValueError``) whose message names the
file, field or parameter at fault and what was expected, so front ends can show it as one line.
"""

from __future__ import annotations

__all__ = ["DVRCancelled", "DVRInputError", "DVRWarning"]


class DVRInputError(ValueError):
    """Bad input: a file, field or parameter that does not meet the documented expectation."""


class DVRWarning(UserWarning):
    """A well-defined but suspicious situation (e.g. a camera that sees none of the volume)."""


class DVRCancelled(RuntimeError):
    """A long step stopped because its ``progress`` callback raised :class:`StopIteration`."""

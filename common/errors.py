"""The one exception type for user mistakes: bad files, bad values, bad options."""

from __future__ import annotations


class DamcapError(Exception):
    """A problem with the user's input or options, reported as one line without a traceback.

    The message names the file, the offending value and, where possible, what to do about it.
    """

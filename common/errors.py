"""The one exception type for user mistakes: bad files, bad values, bad options."""

from __future__ import annotations


class DamcapError(Exception):
    """A problem with the user's input or options, reported as one line without a traceback.

    The message names the file, the offending value and, where possible, what to do about it.
    """


def require_options(options: object, at_least_1: tuple[str, ...] = (), at_least_0: tuple[str, ...] = (),
                    positive_finite: tuple[str, ...] = ()) -> None:
    """Check an options dataclass's numeric fields; the error names the CLI flag and the value.

    >>> from types import SimpleNamespace
    >>> try:
    ...     require_options(SimpleNamespace(steps=0), at_least_1=("steps",))
    ... except DamcapError as e:
    ...     print(e)
    --steps must be >= 1, got 0
    """
    import math

    flag = lambda name: "--" + name.replace("_", "-")  # noqa: E731
    for minimum, names in ((1, at_least_1), (0, at_least_0)):
        for name in names:
            value = getattr(options, name)
            if not value >= minimum:
                raise DamcapError(f"{flag(name)} must be >= {minimum}, got {value}")
    for name in positive_finite:
        value = getattr(options, name)
        if not (value > 0 and math.isfinite(value)):
            raise DamcapError(f"{flag(name)} must be a positive number, got {value}")

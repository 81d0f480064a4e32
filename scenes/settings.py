"""Settings written ``NAME=V1,V2,...``, as {name: values}: the command line's grids and a
unit's settings, read the same way by the library code that takes them as text."""

from __future__ import annotations


def name_values(items: list[str], flag: str, expected: str) -> dict[str, tuple[float, ...]]:
    """``NAME=V1,V2,...`` command-line settings as {name: values}; a ValueError naming
    ``flag``, the setting and what was ``expected`` for anything else."""
    out = {}
    for item in items:
        name, sep, text = item.partition("=")
        try:
            values = tuple(float(x) for x in text.split(","))
        except ValueError:
            values = ()
        if not sep or not name.strip() or not values:
            raise ValueError(f"{flag} {item!r}: expected {expected}")
        out[name.strip()] = values
    return out

"""Lists of names as users write them: ``["reach-v3", "push-v3"]``, ``"reach-v3,push-v3"`` or
``["reach-v3,push-v3", "door-open-v3"]`` (flags, YAML and Python alike). The lowest layer of
the package: it imports nothing of stepnft, so every module may use it."""

from __future__ import annotations

from collections.abc import Iterable


def split_names(value: str | Iterable[str] | None) -> list[str]:
    """The names in ``value`` (a string or strings, each comma-separated), stripped, empty
    ones dropped, in order; None gives ``[]``."""
    if value is None:
        return []
    items = [value] if isinstance(value, str) else value
    return [name.strip() for item in items for name in str(item).split(",") if name.strip()]

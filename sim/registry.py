"""Small named registries, one per extension point (detectron2 style).

A registry maps a name to an entry (a class or a function). Configs pick entries by name; lookups
go through `Registry.get`, which names the valid choices when a name is unknown. Each registry's
docstring says how its entries are called.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Generic, TypeVar

from sim.errors import UserError

T = TypeVar("T")


class Registry(Generic[T]):
    """A name -> entry table.

    Args:
        name: what the entries are ("context layout", "degradation", ...), used in error messages.
        doc: how an entry is called; shown by `describe()`.
    """

    def __init__(self, name: str, doc: str = "") -> None:
        self.name = name
        self.doc = doc
        self._entries: dict[str, T] = {}

    def register(self, name: str | None = None) -> Callable[[T], T]:
        """Decorator: `@REG.register("fog")` (defaults to the entry's `name` attribute or __name__)."""

        def deco(entry: T) -> T:
            key = name or getattr(entry, "name", None) or entry.__name__  # type: ignore[attr-defined]
            if key in self._entries:
                raise KeyError(f"{self.name} {key!r} is registered twice")
            self._entries[key] = entry
            return entry

        return deco

    def add(self, name: str, entry: T) -> T:
        return self.register(name)(entry)

    def get(self, name: str) -> T:
        try:
            return self._entries[name]
        except KeyError:
            raise UserError(
                f"unknown {self.name} {name!r} (choose from: {', '.join(self.names())})"
            ) from None

    def names(self) -> list[str]:
        return list(self._entries)

    def items(self) -> list[tuple[str, T]]:
        return list(self._entries.items())

    def __contains__(self, name: object) -> bool:
        return name in self._entries

    def __iter__(self) -> Iterator[str]:
        return iter(self._entries)

    def __len__(self) -> int:
        return len(self._entries)

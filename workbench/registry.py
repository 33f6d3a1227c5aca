"""One mechanism for the workbench's registries of named records (the methods, the systems,
the scene kinds):
a dict in registration order that looks names up, registers and unregisters with errors that
name the field."""

from __future__ import annotations

from typing import Generic, TypeVar

from workbench.validation import fail

T = TypeVar("T")


class Registry(dict[str, T], Generic[T]):
    """Records of type ``kind`` by their ``name``, in registration order. ``what``: the word
    for one record in messages; ``lookup_field``, ``arg_field``, ``name_field``: the fields an
    unknown name, a record of another type and a taken name are reported under."""

    def __init__(self, what: str, kind: type, lookup_field: str, arg_field: str,
                 name_field: str) -> None:
        super().__init__()
        self.what, self.kind = what, kind
        self.lookup_field, self.arg_field, self.name_field = lookup_field, arg_field, name_field

    def named(self, name: str) -> T:
        """The record ``name``; an unknown name is a ValueError naming the known ones."""
        if not isinstance(name, str) or name not in self:
            raise fail(self.lookup_field, name,
                       f"unknown {self.what}; allowed values are {tuple(self)}")
        return self[name]

    def register(self, record: T) -> T:
        """Add ``record`` under its name, which must be new; returns it."""
        if not isinstance(record, self.kind):
            raise fail(self.arg_field, record, f"must be a {self.kind.__name__}")
        name = record.name  # type: ignore[attr-defined]
        if name in self:
            raise fail(self.name_field, name, "is registered already")
        self[name] = record
        return record

    def unregister(self, name: str) -> T:
        """Remove the record ``name`` (e.g. a test's own); returns it."""
        return self.pop(self.named(name).name)  # type: ignore[attr-defined]

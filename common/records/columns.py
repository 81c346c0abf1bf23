"""Records as columns: many records of one dataclass held as one list per field.

``@columns_of(UpdateStats, rows=N)`` on a subclass of :class:`Columns` declares its fields from
the record's own declaration: a field ``name: T`` becomes the column ``name: list[T]`` (at most
``rows`` items) and a map field ``name: dict[str, V]`` (a record's open statistics) becomes
``name: dict[str, list[V | None]]``, one column per key, None where a row has no such key. The
bounds of ``T`` and ``V`` (:mod:`fedhpg.common.records.limits`) carry over item by item, so a column
is checked against exactly what its records would be, and a field added to the record is a
column at once: there is no second list of fields to keep in step.

The columns read as a sequence of records (``columns[i]``, iteration, :meth:`Columns.records`),
and slice, pick and build from records without leaving the columnar form. Pure Python.
"""

from __future__ import annotations

import dataclasses
import functools
import typing
from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING, Annotated, Any, ClassVar, Generic, Self, TypeVar, overload

from fedhpg.common.records.limits import Bound, bounds_of

R = TypeVar("R")
C = TypeVar("C", bound="type[Columns[Any]]")


@functools.cache
def _fields_of(record: type) -> dict[str, dataclasses.Field[Any]]:
    return {f.name: f for f in dataclasses.fields(record)}


class Columns(Sequence[R], Generic[R]):
    """Records of type :attr:`record` as columns (the fields :func:`columns_of` declared)."""

    record: ClassVar[type]
    """The record type whose fields the columns are."""
    scalar_fields: ClassVar[tuple[str, ...]] = ()
    """Fields with one value per row."""
    map_fields: ClassVar[tuple[str, ...]] = ()
    """Fields that are maps of columns (a record's ``dict[str, V]`` fields)."""

    if TYPE_CHECKING:

        def __init__(self, **columns: Any) -> None: ...

    def __post_init__(self) -> None:
        sizes = {len(getattr(self, name)) for name in self.scalar_fields}
        for name in self.map_fields:
            sizes.update(map(len, getattr(self, name).values()))
        if len(sizes) > 1:  # named only then: every result is checked, few fail
            lengths = {name: len(getattr(self, name)) for name in self.scalar_fields}
            for name in self.map_fields:
                lengths |= {f"{name}[{k!r}]": len(c) for k, c in getattr(self, name).items()}
            raise ValueError(f"columns of different lengths: {lengths}")

    @classmethod
    def of(cls, records: Sequence[R]) -> Self:
        """The columns of ``records``, in order."""
        columns: dict[str, Any] = {
            name: [getattr(r, name) for r in records] for name in cls.scalar_fields
        }
        for name in cls.map_fields:
            maps = [getattr(r, name) for r in records]
            keys = dict.fromkeys(key for own in maps for key in own)
            columns[name] = {key: [own.get(key) for own in maps] for key in keys}
        return cls(**columns)

    @classmethod
    def filled(cls, rows: int, **given: Any) -> Self:
        """``rows`` rows of the ``given`` columns (lists, or anything with ``tolist``: numpy
        arrays), every other field at the record's default."""
        defaults = _fields_of(cls.record)
        columns: dict[str, Any] = {}
        for name in (*cls.scalar_fields, *cls.map_fields):
            if name in given:
                value = given[name]
                columns[name] = value.tolist() if hasattr(value, "tolist") else value
                continue
            field = defaults[name]
            if name in cls.map_fields:
                columns[name] = {}
            elif field.default is not dataclasses.MISSING:
                columns[name] = [field.default] * rows
            else:
                raise TypeError(f"{cls.__name__}.filled: no column and no default for {name!r}")
        unknown = set(given) - set(columns)
        if unknown:
            raise TypeError(f"{cls.__name__}.filled: not fields of the record: {sorted(unknown)}")
        return cls(**columns)

    def _picked(self, pick: Callable[[list[Any]], list[Any]]) -> Self:
        columns: dict[str, Any] = {name: pick(getattr(self, name)) for name in self.scalar_fields}
        for name in self.map_fields:
            columns[name] = {key: pick(c) for key, c in getattr(self, name).items()}
        return type(self)(**columns)

    def replaced(self, **columns: Any) -> Self:
        """These columns with ``columns`` in place of their own."""
        fields = (*self.scalar_fields, *self.map_fields)
        return type(self)(**{name: getattr(self, name) for name in fields} | columns)

    def take(self, rows: Sequence[int]) -> Self:
        """The columns of ``rows`` only, in that order."""
        return self._picked(lambda column: [column[i] for i in rows])

    @classmethod
    def gathered(cls, rows: Sequence[tuple[Self, int]]) -> Self:
        """Row ``j`` of ``rows[i][0]`` as row i, for each i (a map column None where that
        part has none)."""
        columns: dict[str, Any] = {
            name: [getattr(part, name)[j] for part, j in rows] for name in cls.scalar_fields
        }
        for name in cls.map_fields:
            keys = dict.fromkeys(key for part, _ in rows for key in getattr(part, name))
            columns[name] = {
                key: [
                    None if (column := getattr(part, name).get(key)) is None else column[j]
                    for part, j in rows
                ]
                for key in keys
            }
        return cls(**columns)

    @classmethod
    def concatenated(cls, parts: Sequence[Self]) -> Self:
        """The rows of ``parts`` one after another (a map column None where a part has none)."""
        return cls.gathered([(part, j) for part in parts for j in range(len(part))])

    def __len__(self) -> int:
        if self.scalar_fields:
            return len(getattr(self, self.scalar_fields[0]))
        return next((len(c) for n in self.map_fields for c in getattr(self, n).values()), 0)

    @overload
    def __getitem__(self, index: int) -> R: ...

    @overload
    def __getitem__(self, index: slice) -> Self: ...

    def __getitem__(self, index: int | slice) -> R | Self:
        if isinstance(index, slice):
            return self._picked(lambda column: column[index])
        values: dict[str, Any] = {name: getattr(self, name)[index] for name in self.scalar_fields}
        for name in self.map_fields:
            values[name] = {
                key: value
                for key, column in getattr(self, name).items()
                if (value := column[index]) is not None
            }
        record: R = self.record(**values)
        return record

    def __iter__(self) -> Iterator[R]:
        return iter(self.records())

    def records(self) -> list[R]:
        """Every row's record (what ``self[i]`` gives for each i), built in one pass over the
        columns: a server reads hundreds of them from one message."""
        names = self.scalar_fields
        rows: list[dict[str, Any]] = [
            dict(zip(names, values, strict=True))
            for values in zip(*(getattr(self, name) for name in names), strict=True)
        ]
        if not names:
            rows = [{} for _ in range(len(self))]
        for name in self.map_fields:
            columns = getattr(self, name)
            keys = list(columns)
            if not keys:
                for row in rows:
                    row[name] = {}
                continue
            for row, values in zip(rows, zip(*columns.values(), strict=True), strict=True):
                row[name] = {
                    key: value for key, value in zip(keys, values, strict=True) if value is not None
                }
        make = self.record
        return [make(**row) for row in rows]


def _column(hint: Any, rows: int) -> Any:
    """The annotation of a column of values annotated ``hint``."""
    return Annotated[list[hint], Bound(max_len=rows)]


def columns_of(record: type, *, rows: int) -> Callable[[C], C]:
    """Class decorator: declare the columns of ``record``'s fields on a :class:`Columns`
    subclass (at most ``rows`` rows) and make it a frozen dataclass of them."""
    hints = typing.get_type_hints(record, include_extras=True)

    def declare(cls: C) -> C:
        annotations: dict[str, Any] = {}
        scalars, maps = [], []
        for field in dataclasses.fields(record):
            hint = hints[field.name]
            base, bounds = bounds_of(hint)
            if typing.get_origin(base) is dict:
                key, value = typing.get_args(base)
                generic: Any = dict  # the record's key and item types, known at run time only
                column = generic[key, _column(value | None, rows)]
                annotated: Any = Annotated  # metadata from the record, known at run time only
                annotations[field.name] = annotated[(column, *bounds)] if bounds else column
                maps.append(field.name)
            else:
                annotations[field.name] = _column(hint, rows)
                scalars.append(field.name)
        cls.__annotations__ = annotations
        cls.record = record
        cls.scalar_fields, cls.map_fields = tuple(scalars), tuple(maps)
        return typing.cast(C, dataclasses.dataclass(frozen=True, kw_only=True)(cls))

    return declare

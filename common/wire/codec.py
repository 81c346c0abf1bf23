"""One generic, versioned codec for every protocol message: a msgpack header + raw array frames.

Frame 0 is a msgpack map ``{"v": version, "type": kind, "fields": {...}, "arrays": [...]}``.
``fields`` holds every field not annotated ``np.ndarray``, as plain msgpack values (a nested
frozen dataclass, such as ``Update.stats``, as a map of exactly its fields); each entry
``{"field", "dtype", "shape"}`` of ``arrays`` describes one following frame holding that array's
bytes in C order. The payload dataclasses of :mod:`fedhpg.common.wire.protocol` are walked with
``dataclasses.fields`` and their annotations, so adding a message needs no code here. No pickle.

:func:`decode` accepts anything at all and either returns a message whose fields match their
annotations or raises :class:`ProtocolError`, because it runs on bytes from the network.
:func:`encode` applies the same rules to outgoing messages, so a message it accepts is one the
peer will accept. Arrays cross without copies in both directions: encode returns views of the
message's arrays (do not mutate them until the frames are sent) and decode returns read-only
views of the received frames (``np.array(x)`` for a private, writable copy).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import reprlib
import types
import typing
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, TypeAlias

import msgpack
import numpy as np

from fedhpg.common.records.limits import bounds_of
from fedhpg.common.wire.protocol import (
    HEADER_LIMITS,
    HEADER_PER_AGENT,
    MSG_TYPE_OF,
    PAYLOAD_TYPES,
    PROTOCOL_VERSION,
    Message,
)

if TYPE_CHECKING:
    import zmq

MAX_HEADER_BYTES = 1 << 20
"""Cap on frame 0: headers carry ids, settings and statistics, never bulk data."""
DEFAULT_MAX_BYTES = 256 << 20
"""Default cap on a whole message (all frames); callers pass their configured limit."""
MAX_FRAMES = 64
"""Frames beyond this are rejected before any of them is looked at."""
MAX_NESTING = 32
"""Deepest list/dict nesting accepted in header values (bounds recursion on both sides)."""
MAX_NDIM = 32
"""Most dimensions an array may declare."""

WIRE_DTYPES: dict[str, np.dtype] = {
    dtype.str: dtype
    for dtype in (
        np.dtype(name).newbyteorder("<")
        for name in ("float32", "float64", "int32", "int64", "uint8", "bool")
    )
}
"""Array dtypes allowed on the wire (little-endian), by their ``dtype.str``."""
ALLOWED_DTYPES = frozenset(WIRE_DTYPES)

_HEADER_KEYS = frozenset({"v", "type", "fields", "arrays"})
_DESCRIPTOR_KEYS = frozenset({"field", "dtype", "shape"})
_SCALARS: dict[type, str] = {bool: "bool", int: "int", float: "float", str: "str", bytes: "bytes"}
_INT_MIN, _INT_END = -(1 << 63), 1 << 64  # what msgpack can carry
_MAX_ADDRESSABLE = np.iinfo(np.intp).max
_MISSING = object()

Frame: TypeAlias = "bytes | bytearray | memoryview | zmq.Frame"
"""Anything with the buffer protocol: what zmq hands out with ``copy=False`` or ``copy=True``."""

_short = reprlib.Repr()
_short.maxstring = _short.maxother = 40
_short.maxlevel = 2


class ProtocolError(ValueError):
    """A message that cannot be accepted; ``code`` says which rule it broke.

    Codes: ``malformed`` (not a msgpack header map of the expected layout), ``version``,
    ``unknown_type``, ``bad_fields`` (missing, unknown or mistyped header fields), ``bad_array``
    (array descriptors or frames) and ``too_large``. The reason may quote peer data, shortened.
    """

    def __init__(self, code: str, reason: str) -> None:
        super().__init__(reason)
        self.code = code
        self.reason = reason


# --- the message classes, read once per class ------------------------------------------------


@dataclasses.dataclass(frozen=True)
class _Spec:
    name: str
    hint: Any
    is_array: bool


def _is_array_hint(hint: Any) -> bool:
    hint, _ = bounds_of(hint)
    return hint is np.ndarray or typing.get_origin(hint) is np.ndarray  # also npt.NDArray[...]


def _supported(hint: Any) -> bool:
    """Whether :func:`_check` knows this annotation (checked once per class, not per message)."""
    origin = typing.get_origin(hint)
    if origin is typing.Annotated:
        return _supported(typing.get_args(hint)[0])
    if hint is Any or hint is None or hint is type(None) or hint in _SCALARS:
        return True
    if origin in (types.UnionType, typing.Union):
        return all(_supported(arg) for arg in typing.get_args(hint))
    if hint in (dict, list):
        return True
    if _is_record(hint):
        return all(_supported(spec.hint) and not spec.is_array for spec in _specs(hint))
    if origin is dict:
        key, value = typing.get_args(hint)
        return key is str and _supported(value)
    if origin is list:
        return all(_supported(arg) for arg in typing.get_args(hint))
    return False


def _is_record(hint: Any) -> bool:
    """A frozen dataclass nested in a message (e.g. ``Update.stats``): a map on the wire."""
    return isinstance(hint, type) and dataclasses.is_dataclass(hint)


@functools.cache
def _specs(cls: type) -> tuple[_Spec, ...]:
    """The wire layout of a payload class; the annotations are strings, hence get_type_hints."""
    hints = typing.get_type_hints(cls, include_extras=True)
    specs = []
    for f in dataclasses.fields(cls):
        hint = hints[f.name]
        is_array = _is_array_hint(hint)
        if not is_array and not _supported(hint):
            raise TypeError(f"{cls.__name__}.{f.name}: annotation {hint!r} cannot go on the wire")
        specs.append(_Spec(f.name, hint, is_array))
    return tuple(specs)


# --- header values: one checker for both directions ------------------------------------------


def _bad(where: str, problem: str) -> ProtocolError:
    return ProtocolError("bad_fields", f"{where}: {problem}")


def _type_name(value: Any) -> str:
    return type(value).__name__


def _check_plain(value: Any, where: str, depth: int) -> None:
    """What ``Any`` admits: msgpack's plain values, with string keys, nested boundedly."""
    if depth > MAX_NESTING:
        raise _bad(where, f"nested deeper than {MAX_NESTING} levels")
    if value is None or isinstance(value, bool | float | str | bytes):
        return
    if isinstance(value, int):
        if not _INT_MIN <= value < _INT_END:
            raise _bad(where, "integer out of the 64-bit range")
    elif isinstance(value, list):
        for i, item in enumerate(value):
            _check_plain(item, f"{where}[{i}]", depth + 1)
    elif isinstance(value, dict):
        for key, item in value.items():
            if not isinstance(key, str):
                raise _bad(where, f"map key {_short.repr(key)} is not a string")
            _check_plain(item, f"{where}[{key!r}]", depth + 1)
    else:
        raise _bad(where, f"{_type_name(value)} is not a plain msgpack value")


Checker = typing.Callable[[Any, str, int], Any]
"""(value, where, depth) -> the checked value, or ProtocolError: one annotation's check."""
_CHECKERS: dict[int, tuple[Any, Checker]] = {}


def _checker(hint: Any) -> Checker:
    """The check of an annotation, compiled once: the typing introspection costs more than
    the check itself, which runs for every field of every message (a host's batch carries
    hundreds of stats records). Keyed by identity, since hashing an ``Annotated`` hint walks
    it; the entry keeps the hint alive, so its id stays its own (annotations are few and live
    as long as their classes)."""
    entry = _CHECKERS.get(id(hint))
    if entry is not None and entry[0] is hint:
        return entry[1]
    checker = _compile(hint)
    _CHECKERS[id(hint)] = (hint, checker)
    return checker


def _check(value: Any, hint: Any, where: str, depth: int = 0) -> Any:
    """``value`` if it fits ``hint`` (bool is no int; an int is a float), with nested records
    built as their dataclasses; else ProtocolError."""
    return _checker(hint)(value, where, depth)


def _compile(hint: Any) -> Checker:
    origin = typing.get_origin(hint)
    if origin is typing.Annotated:
        return _compile_bounded(*bounds_of(hint))
    if hint is Any:
        return _check_any
    if hint is None or hint is type(None):
        return _check_none
    if origin in (types.UnionType, typing.Union):
        return functools.partial(_check_union, typing.get_args(hint))
    if hint is dict or origin is dict:
        args = typing.get_args(hint)
        item = args[1] if args else Any
        if (rule := _number_rule(item)) is not None:
            return functools.partial(_check_number_dict, item, rule)
        return functools.partial(_check_dict, item)
    if hint is list or origin is list:
        args = typing.get_args(hint)
        item = args[0] if args else Any
        if (rule := _number_rule(item)) is not None:
            return functools.partial(_check_number_list, item, rule)
        return functools.partial(_check_list, item)
    if _is_record(hint):
        return _compile_record(hint)
    if hint is float:
        return _check_float
    if hint is int:
        return _check_int
    if hint in (str, bytes):
        return functools.partial(_check_instance, hint)
    if hint is bool:
        return _check_bool
    raise TypeError(f"unsupported annotation {hint!r}")  # _specs admits only the above


def _compile_bounded(base: Any, bounds: tuple[Any, ...]) -> Checker:
    inner = _checker(base)

    def check(value: Any, where: str, depth: int) -> Any:
        checked = inner(value, where, depth)
        for bound in bounds:
            if (problem := bound.problem(checked)) is not None:
                raise _bad(where, problem)
        return checked

    return check


def _check_any(value: Any, where: str, depth: int) -> Any:
    _check_plain(value, where, depth)
    return value


def _check_none(value: Any, where: str, depth: int) -> Any:
    if value is not None:
        raise _bad(where, f"must be None, got {_type_name(value)}")
    return value


def _check_float(value: Any, where: str, depth: int) -> Any:
    if isinstance(value, float):
        return value
    if not isinstance(value, int) or isinstance(value, bool):
        raise _bad(where, f"must be float, got {_type_name(value)}")
    _check_plain(value, where, depth)
    return value


def _check_int(value: Any, where: str, depth: int) -> Any:
    if not isinstance(value, int) or isinstance(value, bool):
        raise _bad(where, f"must be int, got {_type_name(value)}")
    if not _INT_MIN <= value < _INT_END:
        raise _bad(where, "integer out of the 64-bit range")
    return value


def _check_instance(kind: type, value: Any, where: str, depth: int) -> Any:
    if not isinstance(value, kind):
        raise _bad(where, f"must be {kind.__name__}, got {_type_name(value)}")
    return value


def _check_bool(value: Any, where: str, depth: int) -> Any:
    if not isinstance(value, bool):
        raise _bad(where, f"must be bool, got {_type_name(value)}")
    return value


def _check_union(options: tuple[Any, ...], value: Any, where: str, depth: int) -> Any:
    if value is None and type(None) in options:  # an optional value left out: the usual case
        return None
    others = [o for o in options if o is not None and o is not type(None)]
    if value is not None and len(others) == 1:  # an optional value: its own check says why
        return _check(value, others[0], where, depth)
    for option in options:
        try:
            return _check(value, option, where, depth)
        except ProtocolError:
            continue
    names = " | ".join(getattr(o, "__name__", None) or repr(o) for o in options)
    raise _bad(where, f"must be {names}, got {_type_name(value)}")


def _check_dict(item_hint: Any, value: Any, where: str, depth: int) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise _bad(where, f"must be a map, got {_type_name(value)}")
    if depth >= MAX_NESTING:
        raise _bad(where, f"nested deeper than {MAX_NESTING} levels")
    check = _checker(item_hint)
    checked = {}
    for key, item in value.items():
        if not isinstance(key, str):
            raise _bad(where, f"map key {_short.repr(key)} is not a string")
        checked[key] = check(item, f"{where}[{key!r}]", depth + 1)
    return checked


def _check_list(item_hint: Any, value: Any, where: str, depth: int) -> list[Any]:
    if not isinstance(value, list):
        raise _bad(where, f"must be a list, got {_type_name(value)}")
    if depth >= MAX_NESTING:
        raise _bad(where, f"nested deeper than {MAX_NESTING} levels")
    check = _checker(item_hint)
    return [check(item, f"{where}[{i}]", depth + 1) for i, item in enumerate(value)]


def _check_number_list(
    item_hint: Any, rule: _NumberRule, value: Any, where: str, depth: int
) -> list[Any]:
    """A list of bounded numbers (a batch's agent indices, an ``UpdateColumns`` column:
    hundreds per message), tested as a whole; a list that fails the test goes through the
    generic checks, which say why."""
    if type(value) is list and depth < MAX_NESTING and _all_fit(value, rule):
        return value
    return _check_list(item_hint, value, where, depth)


def _check_number_dict(
    item_hint: Any, rule: _NumberRule, value: Any, where: str, depth: int
) -> dict[str, Any]:
    """A map of bounded numbers (an update's algorithm statistics), as the list above."""
    if (
        type(value) is dict
        and depth < MAX_NESTING
        and all(type(key) is str and _fits(item, rule) for key, item in value.items())
    ):
        return value
    return _check_dict(item_hint, value, where, depth)


_NumberRule = tuple[bool, bool, float | None, float | None, bool]
"""(is float, may be None, low, high, finite) of a bounded number field."""


def _number_rule(hint: Any) -> _NumberRule | None:
    """The rule of a field annotated as a bounded int or float (or such a number or None),
    for the records' fast path; None for anything else."""
    optional = False
    if typing.get_origin(hint) in (types.UnionType, typing.Union):
        args = typing.get_args(hint)
        others = [a for a in args if a is not type(None)]
        if len(args) != 2 or len(others) != 1:
            return None
        optional, hint = True, others[0]
    base, bounds = bounds_of(hint)
    if base not in (int, float) or any(
        b.max_len is not None or b.key_len is not None for b in bounds
    ):
        return None
    lows = [b.low for b in bounds if b.low is not None]
    highs = [b.high for b in bounds if b.high is not None]
    return (
        base is float,
        optional,
        max(lows) if lows else None,
        min(highs) if highs else None,
        any(b.finite for b in bounds),
    )


def _fits(value: Any, rule: _NumberRule) -> bool:
    """Whether ``value`` passes the field's checks (the fast path's test: exactly what the
    generic checks accept)."""
    is_float, optional, low, high, finite = rule
    kind = type(value)
    if kind is float:
        if not is_float or (finite and not math.isfinite(value)):
            return False
    elif kind is int:
        if not _INT_MIN <= value < _INT_END:
            return False
    else:
        return value is None and optional
    return (low is None or value >= low) and (high is None or value <= high)


_INT_KINDS = frozenset({int})
_FLOAT_KIND = frozenset({float})


def _all_fit(values: list[Any], rule: _NumberRule) -> bool:
    """Whether every item passes :func:`_fits`, decided with C-level passes over the list
    (item types, finiteness, min and max) instead of a Python call per item. Lists of ints,
    and of floats where the field must be finite, are decided so; any other (a None of an
    optional column, ints mixed with floats, a float field that admits NaN, which min and
    max cannot order) is tested item by item."""
    if len(values) < 2:  # a lone agent's column: one test, not four passes
        return not values or _fits(values[0], rule)
    is_float, _, low, high, finite = rule
    kinds = set(map(type, values))
    if kinds == _INT_KINDS:
        smallest, largest = min(values), max(values)
        if not (smallest >= _INT_MIN and largest < _INT_END):
            return False
    elif kinds == _FLOAT_KIND and is_float and finite:
        if not all(map(math.isfinite, values)):
            return False
        smallest, largest = min(values), max(values)
    else:
        return all(_fits(item, rule) for item in values)
    return (low is None or smallest >= low) and (high is None or largest <= high)


def _compile_record(cls: type) -> Checker:
    """A map holding exactly the record's fields, each of its type, built into ``cls``.

    Bounded numbers, most of a stats record, are tested inline (one call per record, not
    two per field: a host's batch holds hundreds of records); a value that fails the test
    goes through the generic checks, which say why."""
    fields = [(spec.name, _checker(spec.hint), _number_rule(spec.hint)) for spec in _specs(cls)]
    expected = {name for name, _, _ in fields}

    def check(value: Any, where: str, depth: int) -> Any:
        if not isinstance(value, dict):
            raise _bad(where, f"must be a map of {cls.__name__} fields, got {_type_name(value)}")
        if depth >= MAX_NESTING:
            raise _bad(where, f"nested deeper than {MAX_NESTING} levels")
        if value.keys() != expected:
            missing = sorted(expected - set(value))
            unknown = sorted(_short.repr(k) for k in set(value) - expected)
            raise _bad(where, f"missing fields {missing}, unknown fields {unknown}")
        built = {}
        for name, field, rule in fields:
            item = value[name]
            if rule is None or not _fits(item, rule):
                item = field(item, f"{where}.{name}", depth + 1)
            built[name] = item
        try:
            return cls(**built)
        except (TypeError, ValueError) as error:  # a record that validates in __post_init__
            raise _bad(where, str(error)) from None

    return check


_PLAIN_SCALARS = frozenset({int, float, str, bytes, bool, type(None)})


_RECORD_FIELDS: dict[type, tuple[str, ...] | None] = {}
"""Each type of a header value seen: its dataclass fields' names, or None for no dataclass."""


def _record_fields(kind: type) -> tuple[str, ...] | None:
    """The field names of dataclass ``kind`` (None: not a dataclass), found once a type."""
    if kind not in _RECORD_FIELDS:
        is_record = dataclasses.is_dataclass(kind)
        _RECORD_FIELDS[kind] = (
            tuple(f.name for f in dataclasses.fields(kind)) if is_record else None
        )
    return _RECORD_FIELDS[kind]


def _to_wire(value: Any, where: str, depth: int = 0) -> Any:
    """Outgoing header values as decode will see them: numpy scalars become Python scalars and
    tuples lists, so statistics computed with numpy can be sent as they are."""
    kind = type(value)
    if kind in _PLAIN_SCALARS:  # the common case, first: nothing to convert
        return value
    if depth > MAX_NESTING:
        raise _bad(where, f"nested deeper than {MAX_NESTING} levels")
    if kind is list and all(type(item) in _PLAIN_SCALARS for item in value):
        return value  # a column of plain numbers (the statistics): sent as it is
    if isinstance(value, np.generic):
        return value.item()
    names = _record_fields(kind)
    if names is not None:
        return {
            name: item
            if type(item := getattr(value, name)) in _PLAIN_SCALARS
            else _to_wire(item, f"{where}.{name}", depth + 1)
            for name in names
        }
    if isinstance(value, list | tuple):
        return [
            item if type(item) in _PLAIN_SCALARS else _to_wire(item, f"{where}[{i}]", depth + 1)
            for i, item in enumerate(value)
        ]
    if isinstance(value, dict):
        return {
            key: item
            if type(item) in _PLAIN_SCALARS
            else _to_wire(item, f"{where}[{key!r}]", depth + 1)
            for key, item in value.items()
        }
    return value


# --- encode -----------------------------------------------------------------------------------


def _wire_array(value: Any, where: str) -> np.ndarray:
    """The array as it will travel: allowed dtype, little-endian, C-contiguous (copies only if
    it is not already)."""
    if not isinstance(value, np.ndarray):
        raise ProtocolError("bad_array", f"{where}: must be a numpy array, got {_type_name(value)}")
    wire = value.dtype.newbyteorder("<") if value.dtype.byteorder == ">" else value.dtype
    if wire.str not in WIRE_DTYPES:
        allowed = ", ".join(sorted(str(d) for d in WIRE_DTYPES.values()))
        raise ProtocolError(
            "bad_array", f"{where}: dtype {value.dtype} cannot be sent (allowed: {allowed})"
        )
    if value.ndim > MAX_NDIM:
        raise ProtocolError("bad_array", f"{where}: {value.ndim} dimensions (max {MAX_NDIM})")
    array = value.astype(wire, copy=False)
    # ascontiguousarray would also turn a 0-d array into a 1-d one; 0-d is always contiguous.
    return array if array.flags.c_contiguous else np.ascontiguousarray(array)


def _raw(array: np.ndarray) -> bytes | memoryview:
    return memoryview(array.reshape(-1).view(np.uint8).data) if array.size else b""


def encode(message: Message) -> list[bytes | memoryview]:
    """Frames for ``message``: the header, then one buffer per array field (no copy).

    Raises TypeError for a non-message and ProtocolError for content decode would reject
    (wrong field types, unsupported dtypes, an oversized header).
    """
    cls: type = type(message)
    kind = MSG_TYPE_OF.get(cls)
    if kind is None:
        raise TypeError(f"not a protocol message: {cls.__name__}")
    fields: dict[str, Any] = {}
    descriptors: list[dict[str, Any]] = []
    buffers: list[bytes | memoryview] = []
    for spec in _specs(cls):
        where = f"{kind}.{spec.name}"
        value = getattr(message, spec.name)
        if spec.is_array:
            array = _wire_array(value, where)
            descriptors.append(
                {"field": spec.name, "dtype": array.dtype.str, "shape": list(array.shape)}
            )
            buffers.append(_raw(array))
        else:
            fields[spec.name] = wire = _to_wire(value, where)
            _check(wire, spec.hint, where)
    header = msgpack.packb(
        {"v": PROTOCOL_VERSION, "type": str(kind), "fields": fields, "arrays": descriptors},
        use_bin_type=True,
    )
    limit = HEADER_LIMITS.get(cls, MAX_HEADER_BYTES)
    if len(header) > limit:
        raise ProtocolError("too_large", f"{kind}: header of {len(header)} bytes exceeds {limit}")
    _check_scaled_header(cls, kind, len(header), fields)
    return [header, *buffers]


def _check_scaled_header(cls: type, kind: str, size: int, fields: dict[str, Any]) -> None:
    """A batched answer's header may grow with the agents it lists, no further
    (``HEADER_PER_AGENT``): a batch of one costs what one agent's own message may."""
    per_agent = HEADER_PER_AGENT.get(cls)
    if per_agent is None:
        return
    name, base, each = per_agent
    agents = len(fields[name])
    if size > base + each * agents:
        raise ProtocolError(
            "too_large",
            f"{kind}: header of {size} bytes exceeds {base + each * agents} for {agents} agents",
        )


# --- decode -----------------------------------------------------------------------------------


def _frame_view(frame: Any, index: int) -> memoryview:
    try:
        view = memoryview(frame)  # zmq.Frame, bytes, bytearray, memoryview, ndarray...
    except TypeError:
        raise ProtocolError(
            "malformed", f"frame {index} is a {_type_name(frame)}, not a byte buffer"
        ) from None
    if not view.c_contiguous:
        raise ProtocolError("malformed", f"frame {index} is not a contiguous buffer")
    return view if view.format == "B" and view.ndim == 1 else view.cast("B")


def _frame_views(frames: Any, max_bytes: int) -> list[memoryview]:
    if isinstance(frames, bytes | bytearray | memoryview | str):
        raise ProtocolError("malformed", "expected a sequence of frames, got a single buffer")
    try:
        count = len(frames)
    except TypeError:
        raise ProtocolError(
            "malformed", f"expected a sequence of frames, got {_type_name(frames)}"
        ) from None
    if count == 0:
        raise ProtocolError("malformed", "empty message")
    if count > MAX_FRAMES:
        raise ProtocolError("bad_array", f"{count} frames (max {MAX_FRAMES})")
    views = [_frame_view(frame, i) for i, frame in enumerate(frames)]
    total = sum(view.nbytes for view in views)
    if total > max_bytes:
        raise ProtocolError("too_large", f"message of {total} bytes exceeds the cap of {max_bytes}")
    return views


def _no_ext(code: int, data: bytes) -> Any:
    raise ProtocolError("malformed", f"msgpack extension type {code} is not allowed")


def _unpack_header(frame: memoryview) -> dict[Any, Any]:
    if frame.nbytes > MAX_HEADER_BYTES:
        raise ProtocolError(
            "too_large", f"header of {frame.nbytes} bytes exceeds {MAX_HEADER_BYTES}"
        )
    limit = MAX_HEADER_BYTES
    try:
        header = msgpack.unpackb(
            frame,
            raw=False,
            strict_map_key=True,
            use_list=True,
            ext_hook=_no_ext,
            max_ext_len=0,  # also stops the built-in timestamp extension (-1)
            max_str_len=limit,
            max_bin_len=limit,
            max_array_len=limit,
            max_map_len=limit,
        )
    except ProtocolError:
        raise
    except Exception as error:  # msgpack raises several unrelated types for garbage
        raise ProtocolError(
            "malformed", f"header is not valid msgpack ({_type_name(error)}: {error})"
        ) from None
    if not isinstance(header, dict):
        raise ProtocolError("malformed", f"header must be a map, got {_type_name(header)}")
    return header


def _payload_class(header: dict[Any, Any]) -> type:
    """Check the envelope: the version first, so a newer peer hears why it is not understood."""
    version = header.get("v", _MISSING)
    if version is _MISSING:
        raise ProtocolError("malformed", "header has no protocol version 'v'")
    if type(version) is not int or version != PROTOCOL_VERSION:
        raise ProtocolError(
            "version",
            f"received protocol version {_short.repr(version)}, expected {PROTOCOL_VERSION}",
        )
    if set(header) != _HEADER_KEYS:
        raise ProtocolError(
            "malformed",
            f"header keys must be {sorted(_HEADER_KEYS)}, got "
            f"{_short.repr(sorted(map(str, header)))}",
        )
    kind = header["type"]
    cls = PAYLOAD_TYPES.get(kind) if isinstance(kind, str) else None
    if cls is None:
        raise ProtocolError("unknown_type", f"unknown message type {_short.repr(kind)}")
    if not isinstance(header["fields"], dict) or not isinstance(header["arrays"], list):
        raise ProtocolError("malformed", "header 'fields' must be a map and 'arrays' a list")
    return cls


def _decode_fields(kind: str, specs: Sequence[_Spec], fields: dict[Any, Any]) -> dict[str, Any]:
    expected = {spec.name for spec in specs}
    if set(fields) != expected:
        missing = sorted(expected - set(fields))
        unknown = sorted(_short.repr(k) for k in set(fields) - expected)
        raise ProtocolError(
            "bad_fields", f"{kind}: missing fields {missing}, unknown fields {unknown}"
        )
    return {
        spec.name: _check(fields[spec.name], spec.hint, f"{kind}.{spec.name}") for spec in specs
    }


def _shape(shape: Any, where: str) -> tuple[int, ...]:
    if (
        not isinstance(shape, list)
        or len(shape) > MAX_NDIM
        or not all(type(d) is int and 0 <= d < 1 << 48 for d in shape)
    ):
        raise ProtocolError(
            "bad_array", f"{where}: shape {_short.repr(shape)} is not a list of sizes"
        )
    return tuple(shape)


def _decode_array(descriptor: Any, frame: memoryview, where: str, name: str) -> np.ndarray:
    if not isinstance(descriptor, dict) or set(descriptor) != _DESCRIPTOR_KEYS:
        raise ProtocolError("bad_array", f"{where}: array descriptor {_short.repr(descriptor)}")
    if descriptor["field"] != name:
        raise ProtocolError(
            "bad_array",
            f"{where}: descriptor names {_short.repr(descriptor['field'])}, expected {name!r}",
        )
    dtype_str = descriptor["dtype"]
    dtype = WIRE_DTYPES.get(dtype_str) if isinstance(dtype_str, str) else None
    if dtype is None:
        raise ProtocolError("bad_array", f"{where}: dtype {_short.repr(dtype_str)} is not allowed")
    shape = _shape(descriptor["shape"], where)
    if math.prod(d or 1 for d in shape) * dtype.itemsize > _MAX_ADDRESSABLE:
        # numpy refuses such shapes even with a zero among them
        raise ProtocolError("bad_array", f"{where}: shape {list(shape)} is too big to address")
    expected = math.prod(shape) * dtype.itemsize
    if frame.nbytes != expected:
        raise ProtocolError(
            "bad_array",
            f"{where}: {frame.nbytes} bytes, but dtype {dtype_str} and shape {list(shape)} "
            f"need {expected}",
        )
    # numpy assumes bool bytes are 0 or 1; anything else must not reach arithmetic.
    if dtype.kind == "b" and expected and np.frombuffer(frame, np.uint8).max() > 1:
        raise ProtocolError("bad_array", f"{where}: bool array holds bytes other than 0 and 1")
    array = np.frombuffer(frame, dtype=dtype).reshape(shape)
    array.flags.writeable = False  # a view of the frame, even when the frame is writable
    return array


def _decode_arrays(
    kind: str, specs: Sequence[_Spec], descriptors: list[Any], frames: Sequence[memoryview]
) -> dict[str, np.ndarray]:
    if len(descriptors) != len(specs) or len(frames) != len(specs):
        raise ProtocolError(
            "bad_array",
            f"{kind}: expects {len(specs)} array(s); the header lists {len(descriptors)} and "
            f"{len(frames)} array frame(s) arrived",
        )
    return {
        spec.name: _decode_array(descriptor, frame, f"{kind}.{spec.name}", spec.name)
        for spec, descriptor, frame in zip(specs, descriptors, frames, strict=True)
    }


def _decode(frames: Any, max_bytes: int) -> Message:
    views = _frame_views(frames, max_bytes)
    header = _unpack_header(views[0])
    cls = _payload_class(header)
    kind = str(header["type"])
    limit = HEADER_LIMITS.get(cls, MAX_HEADER_BYTES)
    if views[0].nbytes > limit:
        raise ProtocolError(
            "too_large", f"{kind}: header of {views[0].nbytes} bytes exceeds {limit}"
        )
    specs = _specs(cls)
    values = _decode_fields(kind, [s for s in specs if not s.is_array], header["fields"])
    _check_scaled_header(cls, kind, views[0].nbytes, values)
    values |= _decode_arrays(kind, [s for s in specs if s.is_array], header["arrays"], views[1:])
    try:
        return cls(**values)
    except (TypeError, ValueError) as error:  # a payload class that validates in __post_init__
        raise ProtocolError("bad_fields", f"{kind}: {error}") from None


def decode(frames: Sequence[Frame], *, max_bytes: int = DEFAULT_MAX_BYTES) -> Message:
    """The message in ``frames`` (header frame first, no routing identity).

    Raises ProtocolError, and nothing else, for any input that is not a well-formed message
    of this protocol version; arrays in the result are read-only views of the frames.
    """
    try:
        return _decode(frames, max_bytes)
    except ProtocolError:
        raise
    except Exception as error:  # a safety net: a bad frame must never crash a receive loop
        raise ProtocolError(
            "malformed", f"undecodable message ({_type_name(error)}: {error})"
        ) from error

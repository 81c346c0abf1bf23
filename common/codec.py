"""One generic, versioned codec for every protocol message: msgpack header + raw array frames.

Frame 0 is a msgpack map ``{"v": version, "type": kind, "fields": {...}, "arrays": [...]}``;
each entry of ``arrays`` (field name, dtype string, shape) describes one following frame that
holds the array's bytes as they lie in memory. No pickle, no per-message code: the payload
dataclasses in :mod:`fedhpg.common.protocol` are walked with ``dataclasses.fields``.

:func:`decode` accepts anything and either returns a well-formed message or raises
:class:`ProtocolError` with a reason; decoded arrays are read-only views of the frames.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import types
import typing
from collections.abc import Sequence
from typing import Any

import msgpack
import numpy as np

from fedhpg.common.protocol import MSG_TYPE_OF, PAYLOAD_TYPES, PROTOCOL_VERSION, Message, MsgType

MAX_HEADER_BYTES = 1 << 20
DEFAULT_MAX_BYTES = 256 << 20
ALLOWED_DTYPES = frozenset(
    np.dtype(name).str for name in ("float32", "float64", "int32", "int64", "uint8", "bool")
)
HEADER_KEYS = frozenset({"v", "type", "fields", "arrays"})

Frame = Any  # bytes, memoryview, or zmq.Frame


class ProtocolError(ValueError):
    """A message that cannot be accepted; ``code`` says which rule it broke."""

    def __init__(self, code: str, reason: str) -> None:
        super().__init__(reason)
        self.code = code


@dataclasses.dataclass(frozen=True)
class _FieldSpec:
    name: str
    is_array: bool
    accepts: tuple[type, ...]
    optional: bool


@functools.cache
def _field_specs(cls: type) -> tuple[_FieldSpec, ...]:
    hints = typing.get_type_hints(cls)
    specs = []
    for f in dataclasses.fields(cls):
        hint = hints[f.name]
        if hint is np.ndarray:
            specs.append(_FieldSpec(f.name, True, (), False))
            continue
        args = typing.get_args(hint) if isinstance(hint, types.UnionType) else ()
        optional = type(None) in args
        base = next((a for a in args if a is not type(None)), hint) if args else hint
        origin = typing.get_origin(base) or base
        accepts: tuple[type, ...] = (int, float) if origin is float else (origin,)
        specs.append(_FieldSpec(f.name, False, accepts, optional))
    return tuple(specs)


def encode(message: Message) -> list[Frame]:
    """Frames for ``message``: the header, then one raw buffer per array field."""
    kind = MSG_TYPE_OF.get(type(message))
    if kind is None:
        raise TypeError(f"not a protocol message: {type(message).__name__}")
    fields: dict[str, Any] = {}
    arrays: list[dict[str, Any]] = []
    buffers: list[Frame] = []
    for spec in _field_specs(type(message)):
        value = getattr(message, spec.name)
        if spec.is_array:
            array = np.asarray(value)
            if not array.flags.c_contiguous:  # (ascontiguousarray would also turn 0-d into 1-d)
                array = np.ascontiguousarray(array)
            arrays.append(
                {"field": spec.name, "dtype": array.dtype.str, "shape": list(array.shape)}
            )
            buffers.append(memoryview(array.reshape(-1).view(np.uint8)) if array.size else b"")
        else:
            fields[spec.name] = value
    header = msgpack.packb(
        {"v": PROTOCOL_VERSION, "type": kind.value, "fields": fields, "arrays": arrays},
        use_bin_type=True,
    )
    return [header, *buffers]


def _frame_bytes(frame: Frame) -> memoryview:
    buffer = getattr(frame, "buffer", frame)  # zmq.Frame exposes .buffer
    try:
        return memoryview(buffer).cast("B")
    except TypeError as error:
        raise ProtocolError("malformed", f"frame is not a byte buffer: {error}") from None


def _no_ext(code: int, data: bytes) -> Any:
    raise ProtocolError("malformed", f"msgpack extension type {code} is not allowed")


def _unpack_header(frame: memoryview) -> dict[str, Any]:
    if frame.nbytes > MAX_HEADER_BYTES:
        raise ProtocolError(
            "too_large", f"header of {frame.nbytes} bytes exceeds {MAX_HEADER_BYTES}"
        )
    try:
        header = msgpack.unpackb(
            frame, raw=False, strict_map_key=True, ext_hook=_no_ext, use_list=True
        )
    except ProtocolError:
        raise
    except Exception as error:  # msgpack raises several unrelated types for garbage
        raise ProtocolError(
            "malformed", f"header is not valid msgpack ({type(error).__name__})"
        ) from None
    if not isinstance(header, dict):
        raise ProtocolError("malformed", f"header must be a map, got {type(header).__name__}")
    return header


def _check_value(spec: _FieldSpec, value: Any) -> None:
    if value is None and spec.optional:
        return
    if isinstance(value, bool) and bool not in spec.accepts:
        ok = False
    else:
        ok = isinstance(value, spec.accepts)
    if (
        ok
        and isinstance(value, float)
        and not math.isfinite(value)
        and spec.accepts == (int, float)
    ):
        ok = True  # non-finite statistics are legal header values; parameters travel as arrays
    if not ok:
        names = "/".join(t.__name__ for t in spec.accepts)
        raise ProtocolError(
            "bad_fields", f"field {spec.name!r} must be {names}, got {type(value).__name__}"
        )


def _decode_array(spec: Any, frame: memoryview, name: str) -> np.ndarray:
    if not isinstance(spec, dict) or set(spec) != {"field", "dtype", "shape"}:
        raise ProtocolError("bad_array", f"array descriptor of {name!r} is malformed")
    dtype_str, shape = spec["dtype"], spec["shape"]
    if not isinstance(dtype_str, str) or dtype_str not in ALLOWED_DTYPES:
        raise ProtocolError("bad_array", f"array {name!r}: dtype {dtype_str!r} is not allowed")
    if (
        not isinstance(shape, list)
        or not all(
            isinstance(d, int) and not isinstance(d, bool) and 0 <= d < 1 << 40 for d in shape
        )
        or len(shape) > 8
    ):
        raise ProtocolError("bad_array", f"array {name!r}: shape {shape!r} is not a list of sizes")
    dtype = np.dtype(dtype_str)
    expected = math.prod(shape) * dtype.itemsize
    if frame.nbytes != expected:
        raise ProtocolError(
            "bad_array",
            f"array {name!r}: {frame.nbytes} bytes do not fit dtype {dtype_str} and shape {shape}",
        )
    return np.frombuffer(frame, dtype=dtype).reshape(shape)


def decode(frames: Sequence[Frame], *, max_bytes: int = DEFAULT_MAX_BYTES) -> Message:
    """The message in ``frames``; :class:`ProtocolError` for anything else."""
    if not frames:
        raise ProtocolError("malformed", "empty message")
    views = [_frame_bytes(frame) for frame in frames]
    total = sum(view.nbytes for view in views)
    if total > max_bytes:
        raise ProtocolError("too_large", f"message of {total} bytes exceeds the cap of {max_bytes}")
    header = _unpack_header(views[0])
    if set(header) != HEADER_KEYS:
        raise ProtocolError(
            "malformed",
            f"header keys must be {sorted(HEADER_KEYS)}, got {sorted(map(str, header))}",
        )
    version = header["v"]
    if version != PROTOCOL_VERSION:
        raise ProtocolError(
            "version", f"protocol version {version!r} received, {PROTOCOL_VERSION} expected"
        )
    kind = header["type"]
    try:
        cls = PAYLOAD_TYPES[MsgType(kind)]
    except (ValueError, TypeError):
        raise ProtocolError("unknown_type", f"unknown message type {kind!r}") from None
    fields, arrays = header["fields"], header["arrays"]
    if not isinstance(fields, dict) or not isinstance(arrays, list):
        raise ProtocolError("malformed", "header 'fields' must be a map and 'arrays' a list")
    specs = _field_specs(cls)
    array_specs = [s for s in specs if s.is_array]
    value_specs = {s.name: s for s in specs if not s.is_array}
    if set(fields) != set(value_specs):
        missing = sorted(set(value_specs) - set(fields))
        unknown = sorted(map(str, set(fields) - set(value_specs)))
        raise ProtocolError(
            "bad_fields", f"{kind}: missing fields {missing}, unknown fields {unknown}"
        )
    if len(arrays) != len(array_specs) or len(views) != 1 + len(array_specs):
        raise ProtocolError(
            "bad_array",
            f"{kind}: expected {len(array_specs)} array frame(s), header lists {len(arrays)} and "
            f"{len(views) - 1} arrived",
        )
    values: dict[str, Any] = {}
    for name, spec in value_specs.items():
        _check_value(spec, fields[name])
        values[name] = fields[name]
    for spec, descriptor, view in zip(array_specs, arrays, views[1:], strict=True):
        if not isinstance(descriptor, dict) or descriptor.get("field") != spec.name:
            raise ProtocolError(
                "bad_array", f"{kind}: array frames out of order (expected {spec.name!r})"
            )
        values[spec.name] = _decode_array(descriptor, view, spec.name)
    return cls(**values)

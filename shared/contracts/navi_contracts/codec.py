"""The one codec for every wire message: msgpack, with an extension type for numpy arrays.

Envelope: a msgpack map `{"type": <model name>, "v": <schema version>, "data": <fields>}`.
A numpy array is msgpack extension type 1 whose payload is
`u16 header length | msgpack [dtype string, shape] | raw little-endian bytes (C order)`.
Decoding returns arrays as read-only views over the extension bytes (no per-array copy).

Anything wrong with a payload (garbage, truncation, an oversized payload, an unknown type or
schema version, a wrong dtype or shape, a value a model rejects) raises `ContractError`, and no
partially filled model ever escapes.
"""

from __future__ import annotations

import struct
from typing import Any, TypeVar

import msgpack
import numpy as np
import pydantic

from navi_contracts.models import MESSAGE_TYPES, Message

ARRAY_EXT = 1
MAX_PAYLOAD_BYTES = 256 * 1024 * 1024
ALLOWED_DTYPES = frozenset(
    np.dtype(d).str
    for d in (
        "bool",
        "int8",
        "uint8",
        "int16",
        "uint16",
        "int32",
        "uint32",
        "int64",
        "uint64",
        "float16",
        "float32",
        "float64",
    )
)
_BY_NAME: dict[str, type[Message]] = {t.__name__: t for t in MESSAGE_TYPES}
_HEADER = struct.Struct("<H")

M = TypeVar("M", bound=Message)


class ContractError(ValueError):
    """A payload that is not a valid message of the expected contract."""


def _pack_array(arr: np.ndarray) -> msgpack.ExtType:
    if arr.dtype.str.replace(">", "<") not in ALLOWED_DTYPES and arr.dtype.str not in ALLOWED_DTYPES:
        raise ContractError(f"dtype {arr.dtype} cannot go on the wire")
    little = arr.astype(arr.dtype.newbyteorder("<"), copy=False) if arr.dtype.byteorder == ">" else arr
    header = msgpack.packb([little.dtype.str, list(little.shape)])
    return msgpack.ExtType(
        ARRAY_EXT, _HEADER.pack(len(header)) + header + np.ascontiguousarray(little).tobytes()
    )


def _unpack_array(code: int, payload: bytes) -> Any:
    if code != ARRAY_EXT:
        raise ContractError(f"unknown extension type {code}")
    if len(payload) < _HEADER.size:
        raise ContractError("truncated array header")
    (hlen,) = _HEADER.unpack_from(payload)
    header = msgpack.unpackb(payload[_HEADER.size : _HEADER.size + hlen])
    if not (isinstance(header, list) and len(header) == 2 and isinstance(header[0], str)):
        raise ContractError("malformed array header")
    dtype_str, shape = header
    if dtype_str not in ALLOWED_DTYPES:
        raise ContractError(f"dtype {dtype_str!r} is not allowed on the wire")
    if not (
        isinstance(shape, list) and all(isinstance(s, int) and s >= 0 for s in shape) and len(shape) <= 8
    ):
        raise ContractError("malformed array shape")
    dtype = np.dtype(dtype_str)
    count = int(np.prod(shape, dtype=np.int64))
    body = memoryview(payload)[_HEADER.size + hlen :]
    if body.nbytes != count * dtype.itemsize:
        raise ContractError(
            f"array holds {body.nbytes} bytes, shape {shape} of {dtype} needs {count * dtype.itemsize}"
        )
    return np.frombuffer(body, dtype=dtype, count=count).reshape(shape)  # view, read-only


def _default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return _pack_array(obj)
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"cannot encode {type(obj).__name__}")


def encode(message: Message) -> bytes:
    """Serialise a contract model to msgpack bytes."""
    envelope = {
        "type": type(message).__name__,
        "v": message.schema_version_of(),
        "data": message.model_dump(mode="python"),
    }
    return msgpack.packb(envelope, default=_default, use_bin_type=True)


def _unpack_envelope(payload: bytes | bytearray | memoryview, max_bytes: int) -> dict[str, Any]:
    if len(payload) > max_bytes:
        raise ContractError(f"payload of {len(payload)} bytes exceeds the {max_bytes}-byte limit")
    try:
        envelope = msgpack.unpackb(payload, ext_hook=_unpack_array, raw=False, strict_map_key=True)
    except ContractError:
        raise
    except Exception as exc:  # msgpack raises several unrelated types on garbage; all mean "not a message"
        raise ContractError(f"not a msgpack message: {exc}") from exc
    if not isinstance(envelope, dict) or set(envelope) != {"type", "v", "data"}:
        raise ContractError("payload is not a message envelope")
    if not isinstance(envelope["data"], dict):
        raise ContractError("message data is not a map")
    return envelope


def _validate(envelope: dict[str, Any], model_type: type[M]) -> M:
    if envelope["type"] != model_type.__name__:
        raise ContractError(f"expected a {model_type.__name__}, got {envelope['type']!r}")
    if envelope["v"] != model_type.schema_version_of():
        raise ContractError(
            f"{model_type.__name__} schema version {envelope['v']!r} is not supported "
            f"(this build reads version {model_type.schema_version_of()})"
        )
    try:
        return model_type.model_validate(envelope["data"])
    except pydantic.ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise ContractError(f"invalid {model_type.__name__}: {where}: {first['msg']}") from exc


def decode(
    payload: bytes | bytearray | memoryview, model_type: type[M], *, max_bytes: int = MAX_PAYLOAD_BYTES
) -> M:
    """Parse and validate `payload` as a `model_type`; raise `ContractError` for anything else."""
    return _validate(_unpack_envelope(payload, max_bytes), model_type)


def decode_any(payload: bytes | bytearray | memoryview, *, max_bytes: int = MAX_PAYLOAD_BYTES) -> Message:
    """Decode a payload of any known message type (for recorders and generic tools)."""
    envelope = _unpack_envelope(payload, max_bytes)
    name = envelope["type"]
    if not isinstance(name, str) or name not in _BY_NAME:
        raise ContractError(f"unknown message type {name!r}")
    return _validate(envelope, _BY_NAME[name])

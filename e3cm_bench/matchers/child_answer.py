"""The answer of a StoppableWorker's child (guards.py), in a form that cannot run code in the
parent or make it allocate or wait without bound.

The child runs a matcher, which is someone else's code; whatever that code writes on the socket
is read by the parent. A pickle would let it run code in the parent, or take any time to load;
so an answer is a fixed header, a small JSON document and raw array bytes:

    header   16-byte nonce of the call it answers | JSON length | array bytes (ANSWER_HEADER)
    JSON     the value: numbers, strings, lists, dicts, Matches, and references to arrays,
             each array declared by dtype (plain numbers only) and shape
    arrays   their bytes, one after the other

The parent checks both lengths against its bounds before reading a byte of them, and the
declared arrays against the bytes announced before building any; an answer with another call's
nonce (a spare one the matcher wrote) is read past, never taken for this call's.
"""

from __future__ import annotations

import builtins
import json
import struct
from typing import Any

import numpy as np

from e3cm_bench.ground.matches import Matches

ANSWER_HEADER = struct.Struct("!16sQQ")
NONCE_BYTES = 16
MAX_JSON_BYTES = 4 << 20  # the structure only (arrays go raw): a matcher's info is a few kB
# Array bytes of one answer: cache.MAX_PAIR_MATCHES matches (N x 2 + N x 2 + N float32: 200 MB), with room.
MAX_ARRAY_BYTES = 256 << 20
ARRAY_KINDS = "biuf"  # bool, integers, floats: no objects, strings or structured types
MAX_ERROR_CHARS = 2000


class BadAnswer(ValueError):
    """An answer that breaks the format or its bounds."""


# --------------------------------------------------------------------------- the child's side


def encode(nonce: bytes, value: Any) -> bytes:
    """The frame of an answer ("ok", value) or ("error", exception); a value that cannot be sent
    becomes an error answer naming what it held."""
    kind, payload = value
    arrays: list[np.ndarray] = []
    try:
        document = {"error": _error(payload)} if kind == "error" else {"ok": _tree(payload, arrays)}
        text = json.dumps(document).encode()
    except (TypeError, ValueError, RecursionError) as exc:
        arrays = []
        text = json.dumps({"error": _error(RuntimeError(f"its answer cannot be sent back ({exc})"))}).encode()
    data = b"".join(np.ascontiguousarray(a).tobytes() for a in arrays)
    return ANSWER_HEADER.pack(nonce, len(text), len(data)) + text + data


def _tree(value: Any, arrays: list) -> Any:
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, np.generic) and value.dtype.kind in ARRAY_KINDS:
        return value.item()
    if isinstance(value, np.ndarray):
        if value.dtype.kind not in ARRAY_KINDS:
            raise TypeError(f"an array of dtype {value.dtype}")
        arrays.append(value)
        return {"a": [len(arrays) - 1, value.dtype.str, list(value.shape)]}
    if isinstance(value, Matches):
        return {"m": [_tree(v, arrays) for v in (value.keypoints0, value.keypoints1, value.scores, value.info)]}
    if isinstance(value, (list, tuple)):
        return {"t" if isinstance(value, tuple) else "l": [_tree(v, arrays) for v in value]}
    if isinstance(value, dict) and all(isinstance(k, str) for k in value):
        return {"d": {k: _tree(v, arrays) for k, v in value.items()}}
    raise TypeError(f"a {type(value).__name__}")


def _error(exc: BaseException) -> dict:
    args = [a for a in exc.args if isinstance(a, (str, int, float))] if len(exc.args) <= 8 else []
    return {"type": type(exc).__name__, "args": [a[:MAX_ERROR_CHARS] if isinstance(a, str) else a for a in args],
            "text": str(exc)[:MAX_ERROR_CHARS]}


# --------------------------------------------------------------------------- the parent's side


def check_lengths(json_bytes: int, array_bytes: int, max_array_bytes: int) -> None:
    if json_bytes > MAX_JSON_BYTES:
        raise BadAnswer(f"it announced {json_bytes} bytes of description (at most {MAX_JSON_BYTES})")
    if array_bytes > max_array_bytes:
        raise BadAnswer(f"it announced {array_bytes} bytes of arrays (at most {max_array_bytes})")


def declared_arrays(text: bytes, array_bytes: int) -> tuple[Any, list[tuple[np.dtype, tuple]]]:
    """The JSON document, and its arrays' (dtype, shape) in order; BadAnswer where they do not
    add up to `array_bytes` exactly. Nothing is allocated for the arrays here."""
    try:
        document = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise BadAnswer(f"its description is not readable ({type(exc).__name__})") from None
    if not isinstance(document, dict) or len(document) != 1 or next(iter(document)) not in ("ok", "error"):
        raise BadAnswer("its description is neither a result nor an error")
    declared: list = []
    try:
        _collect(document, declared)
    except RecursionError:
        raise BadAnswer("its description is nested too deeply") from None
    total = sum(dtype.itemsize * int(np.prod(shape, dtype=np.int64)) for dtype, shape in declared)
    if total != array_bytes:
        raise BadAnswer(f"its arrays declare {total} bytes, it announced {array_bytes}")
    return document, declared


def _collect(node: Any, declared: list) -> None:
    if isinstance(node, dict):
        if set(node) == {"a"}:
            index, dtype, shape = _array_ref(node["a"])
            if index != len(declared):
                raise BadAnswer("its arrays are declared out of order")
            declared.append((dtype, shape))
            return
        for value in node.values():
            _collect(value, declared)
    elif isinstance(node, list):
        for value in node:
            _collect(value, declared)


def _array_ref(ref: Any) -> tuple[int, np.dtype, tuple]:
    try:
        index, dtype, shape = ref
        dtype = np.dtype(str(dtype))
        shape = tuple(int(n) for n in shape)
    except (TypeError, ValueError):
        raise BadAnswer("it declares an array without a dtype and shape") from None
    if dtype.kind not in ARRAY_KINDS or dtype.fields is not None or dtype.subdtype is not None:
        raise BadAnswer(f"it declares an array of dtype {dtype}")
    if len(shape) > 8 or any(n < 0 or n > MAX_ARRAY_BYTES for n in shape):
        raise BadAnswer(f"it declares an array of shape {shape}")
    return int(index), dtype, shape


def decode(document: dict, declared: list, data: bytes | bytearray, errors: dict[str, type]) -> Any:
    """The value of an ok answer; an error answer raised as the exception it names (a class in
    `errors` or a built-in one; else a RuntimeError with its type and message)."""
    offset, arrays = 0, []
    for dtype, shape in declared:
        count = int(np.prod(shape, dtype=np.int64))
        arrays.append(np.frombuffer(data, dtype, count, offset).reshape(shape).copy())
        offset += count * dtype.itemsize
    if "error" in document:
        raise _exception(document["error"], errors)
    try:
        return _value(document["ok"], arrays)
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise BadAnswer(f"its value is malformed ({type(exc).__name__}: {exc})") from None


def _value(node: Any, arrays: list) -> Any:
    if not isinstance(node, dict):
        return node
    (tag, body), = node.items()
    if tag == "a":
        return arrays[int(body[0])]
    if tag == "m":
        return Matches(*(_value(v, arrays) for v in body))
    if tag in ("l", "t"):
        items = [_value(v, arrays) for v in body]
        return tuple(items) if tag == "t" else items
    if tag == "d":
        return {str(k): _value(v, arrays) for k, v in body.items()}
    raise ValueError(f"unknown tag {tag!r}")


def _exception(error: Any, errors: dict[str, type]) -> BaseException:
    if not isinstance(error, dict):
        return BadAnswer("its error is malformed")
    name, text = str(error.get("type", "")), str(error.get("text", ""))[:MAX_ERROR_CHARS]
    args = error.get("args") if isinstance(error.get("args"), list) else [text]
    cls = errors.get(name) or getattr(builtins, name, None)
    if isinstance(cls, type) and issubclass(cls, Exception):  # never SystemExit or KeyboardInterrupt here
        try:
            return cls(*args)
        except Exception:  # noqa: BLE001 - a class whose __init__ wants other arguments
            pass
    return RuntimeError(f"{name}: {text}")

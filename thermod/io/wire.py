"""Wire format v1 codec: messages as bytes, without any transport (docs/wire.md).

Every message is three frames ``[topic, header, payload]``: an exact topic (`TOPICS`), a UTF-8 JSON
header and the raw C-contiguous array bytes. This module builds and checks them; the ZeroMQ sockets
that carry them live in `thermod.runtime.publish`. Nothing here imports zmq: `decode` accepts any
objects that expose the buffer protocol (bytes, memoryview, ``zmq.Frame``).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable

import numpy as np

from thermod.errors import ThermodError
from thermod.io.json_safe import jsonable

WIRE_VERSION = 1
TOPICS = ("frame", "raw", "gyro", "health", "kernel", "celsius")
# Array dtypes a payload may carry (little-endian numpy strings); "packed" = concatenated `layout` parts.
ARRAY_DTYPES = ("<f4", "<u2", "|u1", "<f8", "<i8")
PACKED = "packed"
GYRO_LAYOUT_DTYPES = {"t": "<f8", "rate": "<f4"}
GYRO_DTYPE = np.dtype([("t", "<f8"), ("rate", "<f4", (3,))])
MAX_HEADER_BYTES = 65536
# Largest payload a subscriber accepts by default: a 4096 × 4096 float32 frame.
MAX_PAYLOAD_BYTES = 4096 * 4096 * 4

assert not any(a != b and b.startswith(a) for a in TOPICS for b in TOPICS), "a topic prefixes another"


class MessageError(ThermodError, ValueError):
    """A received message violates wire v1 (counted by `kind` and logged by `Subscriber`, never raised
    out of it). `kind`: framing, topic, header_size, json, version, header, dtype, shape, layout,
    payload_size."""

    def __init__(self, kind: str, message: str):
        self.kind = kind
        super().__init__(message)


# ------------------------------------------------------------------------------------------ encode
def encode_header(header: dict) -> bytes:
    """The header frame: compact UTF-8 JSON. Raises TypeError/ValueError if it cannot be serialised."""
    return json.dumps(jsonable(header), separators=(",", ":"), allow_nan=False).encode()


def wire_array(array: np.ndarray | None, *, copy: bool = True) -> np.ndarray:
    """``array`` as the payload it travels as: little-endian, C-contiguous, an allowed dtype.

    None means an empty payload (uint8, shape [0]). Copies unless ``copy=False`` and the array
    already has the wire layout (then the caller hands the buffer over and must not write to it).
    """
    if array is None:
        return np.empty(0, np.uint8)
    array = np.asarray(array)
    dtype = array.dtype.newbyteorder("<") if array.dtype.byteorder == ">" else array.dtype
    if dtype.str not in ARRAY_DTYPES:
        raise ValueError(f"payload dtype {array.dtype} not allowed on the wire (allowed: {ARRAY_DTYPES})")
    if copy or not array.flags.c_contiguous or array.dtype != dtype:
        array = np.array(array, dtype=dtype, order="C", copy=True)
    return array


def array_header(header: dict, array: np.ndarray) -> dict:
    """A copy of ``header`` with the payload's ``shape`` and ``dtype`` (``deblurred`` defaults to false)."""
    head = dict(header)
    head.setdefault("deblurred", False)
    head.update(shape=list(array.shape), dtype=array.dtype.str)
    return head


def pack_gyro(t: np.ndarray, rate: np.ndarray) -> tuple[dict, bytes]:
    """A gyro batch → (header fields ``shape``, ``dtype``, ``n``, ``layout``; payload bytes).

    Payload: ``t`` as <f8 [N] followed by ``rate`` as <f4 [N, 3]."""
    t = np.ascontiguousarray(t, dtype="<f8").ravel()
    rate = np.ascontiguousarray(rate, dtype="<f4")
    n = len(t)
    if rate.shape != (n, 3):
        raise ValueError(f"gyro rate must be [{n}, 3] to match t, got {rate.shape}")
    fields = dict(shape=[n], dtype=PACKED, n=n, layout=[["t", "<f8", [n]], ["rate", "<f4", [n, 3]]])
    return fields, t.tobytes() + rate.tobytes()


def pack_kernel(kernel) -> tuple[dict, np.ndarray]:
    """A blur kernel (``weights`` float32 [kh, kw] summing to 1, ``origin`` (oy, ox) = zero displacement)
    or a grid of them (``kernels[r][c]``) → (header fields ``origin``, ``extent_px``, ``coverage``;
    float32 payload).

    A grid travels as [rows, cols, KH, KW]: every cell zero-padded so that all share one ``origin``
    (weights keep their displacements, so cells compare pixel for pixel)."""
    if hasattr(kernel, "kernels"):
        cells = kernel.kernels
        (oy, ox), (kh, kw) = kernel.common_frame
        out = np.zeros((len(cells), len(cells[0]), kh, kw), "<f4")
        for r, row in enumerate(cells):
            for c, k in enumerate(row):
                y0, x0 = oy - k.origin[0], ox - k.origin[1]
                out[r, c, y0:y0 + k.weights.shape[0], x0:x0 + k.weights.shape[1]] = k.weights
        fields = dict(origin=[oy, ox], extent_px=float(kernel.max_extent_px), coverage=float(kernel.coverage))
        return fields, out
    w = np.ascontiguousarray(kernel.weights, dtype="<f4")
    fields = dict(origin=[int(o) for o in kernel.origin], extent_px=float(kernel.extent_px),
                  coverage=float(kernel.coverage))
    return fields, w


# a `frame` header's ``method``: how the governor's rung deblurred it (docs/wire.md)
METHODS = ("temporal", "kf", "kf_fast", "wiener", "wiener_half")
# a passed-through `frame` header's ``reason``: why it was not deblurred (docs/wire.md)
REASONS = ("disabled", "ffc", "gyro_offline", "gyro_incomplete", "gyro_gap", "kernel_error", "overload",
           "worker_error")


def frame_method_fields(method: str | None, grid) -> dict:
    """The ``frame`` header fields naming how a frame was deblurred: ``method`` (one of `METHODS`,
    null when passed through) and ``grid`` ([rows, cols] of its kernel grid, [1, 1] = one kernel;
    null when passed through). Added in wire v1 without a version change: subscribers ignore keys
    they do not know, and a header without them is from a daemon before the governor."""
    return {"method": method, "grid": None if grid is None else [int(grid[0]), int(grid[1])]}


def nbytes(payload) -> int:
    return payload.nbytes if isinstance(payload, np.ndarray) else len(payload)


# ------------------------------------------------------------------------------------------ decode
def decode(frames: list, *, max_header_bytes: int = MAX_HEADER_BYTES, topics: Iterable[str] = TOPICS):
    """Validate and decode one received multipart message → (topic, header, array).

    ``frames`` are bytes-like objects (bytes, memoryview, ``zmq.Frame``). Raises `MessageError` naming
    what is wrong, and nothing else. The array is a read-only view on the payload (no copy); ``gyro``
    decodes to a structured array with fields ``t`` (<f8) and ``rate`` (<f4, 3); ``health`` to an
    empty uint8 array.
    """
    topics = tuple(topics)
    try:
        n_frames = len(frames)
    except TypeError:
        raise MessageError("framing", f"expected a list of 3 frames, got {type(frames).__name__}") from None
    if n_frames != 3:
        raise MessageError("framing", f"expected 3 frames [topic, header, payload], got {n_frames}")
    try:
        raw_topic, raw_header, payload = (memoryview(f).cast("B") for f in frames)
    except TypeError as e:
        raise MessageError("framing", f"a frame is not a byte buffer ({e})") from None
    topic = bytes(raw_topic).decode("ascii", "replace")
    if topic not in topics:
        raise MessageError("topic", f"topic {topic!r} is not one of {topics}")
    if raw_header.nbytes > max_header_bytes:
        raise MessageError("header_size", f"{topic}: header is {raw_header.nbytes} bytes, "
                                          f"limit {max_header_bytes}")
    try:
        header = json.loads(bytes(raw_header).decode("utf-8"), parse_constant=_reject_constant)
    except RecursionError:  # "[[[[…": the bound on header bytes does not bound the nesting
        raise MessageError("json", f"{topic}: header JSON is nested too deeply") from None
    except (UnicodeDecodeError, ValueError) as e:
        raise MessageError("json", f"{topic}: header is not UTF-8 JSON ({e})") from None
    if not isinstance(header, dict):
        raise MessageError("json", f"{topic}: header must be a JSON object, got {type(header).__name__}")
    if type(header.get("v")) is not int or header["v"] != WIRE_VERSION:  # true == 1 in Python
        raise MessageError("version", f"{topic}: header v={header.get('v')!r}, expected {WIRE_VERSION}")
    seq = header.get("seq")
    if not isinstance(seq, int) or isinstance(seq, bool) or seq < 0:
        raise MessageError("header", f"{topic}: header seq must be a non-negative integer, got {seq!r}")
    for key in ("t", "published"):
        if not _is_number(header.get(key)):
            raise MessageError("header", f"{topic}: header {key!r} must be a number (s), "
                                         f"got {header.get(key)!r}")
    if not isinstance(header.get("deblurred"), bool):
        raise MessageError("header", f"{topic}: header 'deblurred' must be true/false, "
                                     f"got {header.get('deblurred')!r}")
    shape = _shape(topic, "shape", header.get("shape"))
    dtype = header.get("dtype")
    if dtype == PACKED:
        return topic, header, _decode_packed(topic, header, shape, payload)
    if not isinstance(dtype, str) or dtype not in ARRAY_DTYPES:
        raise MessageError("dtype", f"{topic}: dtype {dtype!r} not allowed (expected one of {ARRAY_DTYPES})")
    need = math.prod(shape) * np.dtype(dtype).itemsize
    if need != payload.nbytes:
        raise MessageError("payload_size", f"{topic}: payload is {payload.nbytes} bytes, shape {shape} × "
                                           f"{dtype} needs {need}")
    if topic in ("frame", "raw", "celsius") and len(shape) != 2:
        raise MessageError("shape", f"{topic}: shape must be [H, W], got {shape}")
    if topic == "kernel" and len(shape) not in (2, 4):
        raise MessageError("shape", f"{topic}: shape must be [kh, kw] or [rows, cols, kh, kw], got {shape}")
    array = np.frombuffer(payload, dtype=dtype).reshape(shape)
    array.flags.writeable = False  # a view on the transport's message buffer
    return topic, header, array


def _decode_packed(topic: str, header: dict, shape: list, payload: memoryview) -> np.ndarray:
    layout = header.get("layout")
    if topic != "gyro" or not isinstance(layout, list) or len(shape) != 1:
        raise MessageError("layout", f"{topic}: packed payload needs topic 'gyro', shape [N] and a layout")
    n = shape[0]
    parts, offset = {}, 0
    for entry in layout:
        if not (isinstance(entry, list) and len(entry) == 3):
            raise MessageError("layout", f"{topic}: layout entries are [name, dtype, shape], got {entry!r}")
        name, dt, sub = entry
        want = GYRO_LAYOUT_DTYPES.get(name) if isinstance(name, str) else None
        if want is None or want != dt:
            raise MessageError("layout", f"{topic}: layout entry {name!r} must be one of "
                                         f"{GYRO_LAYOUT_DTYPES} with its dtype, got dtype {dt!r}")
        if name in parts:
            raise MessageError("layout", f"{topic}: layout entry {name!r} appears twice")
        sub = _shape(topic, f"layout[{name}]", sub)
        if not sub or sub[0] != n or (name == "rate" and sub[1:] != [3]) or (name == "t" and len(sub) != 1):
            raise MessageError("layout", f"{topic}: layout {name} shape {sub} does not fit {n} samples")
        size = math.prod(sub) * np.dtype(dt).itemsize
        if offset + size > payload.nbytes:
            raise MessageError("payload_size", f"{topic}: payload is {payload.nbytes} bytes, "
                                               "layout needs more")
        parts[name] = np.frombuffer(payload, dtype=dt, count=math.prod(sub), offset=offset).reshape(sub)
        offset += size
    if offset != payload.nbytes or set(parts) != set(GYRO_LAYOUT_DTYPES):
        raise MessageError("payload_size", f"{topic}: layout {[e[0] for e in layout]} covers {offset} of "
                                           f"{payload.nbytes} payload bytes; expected exactly t and rate")
    out = np.empty(n, dtype=GYRO_DTYPE)
    out["t"], out["rate"] = parts["t"], parts["rate"]
    out.flags.writeable = False
    return out


def _reject_constant(name):
    raise ValueError(f"non-standard JSON constant {name}")


def _is_number(x) -> bool:
    if isinstance(x, bool):
        return False
    return isinstance(x, int) or (isinstance(x, float) and math.isfinite(x))  # int: isfinite overflows


def _shape(topic, key, shape) -> list:
    if not (isinstance(shape, list) and len(shape) <= 4
            and all(isinstance(s, int) and not isinstance(s, bool) and 0 <= s < 2**31 for s in shape)):
        raise MessageError("shape", f"{topic}: header {key!r} must be a list of ≤ 4 non-negative ints, "
                                    f"got {shape!r}")
    return shape

"""ZeroMQ transport, wire format v1 (DESIGN.md §4, docs/wire.md).

The daemon binds one PUB socket; every message is three frames ``[topic, header, payload]``:
an exact topic (``frame``, ``raw``, ``gyro``, ``health``), a UTF-8 JSON header and the raw
C-contiguous array bytes. `Publisher` owns that socket in one thread and never blocks its callers;
`Subscriber` validates every message and counts sequence gaps.

Example (a subscriber on the same host)::

    from thermod.runtime.publish import Subscriber

    with Subscriber("tcp://127.0.0.1:5555", topics=("frame", "health")) as sub:
        for topic, header, array in sub:          # array is read-only, owned by the message
            if topic == "frame":
                print(header["frame_id"], header["deblurred"], array.shape, array.dtype)
            print("lost so far:", sub.gaps)

Security: the default endpoint is loopback only. With ``curve_secret_key_file`` (a file written by
``zmq.auth.create_certificates``) the publisher encrypts with CURVE; with ``authorized_keys_dir`` it
also admits only clients whose public keys are in that directory.
"""

from __future__ import annotations

import collections
import json
import logging
import math
import os
import threading
import time
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np
import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator

from thermod.errors import ThermodError

log = logging.getLogger(__name__)

WIRE_VERSION = 1
DEFAULT_ENDPOINT = "tcp://127.0.0.1:5555"
TOPICS = ("frame", "raw", "gyro", "health")
# Array dtypes a payload may carry (little-endian numpy strings); "packed" = concatenated `layout` parts.
ARRAY_DTYPES = ("<f4", "<u2", "|u1", "<f8", "<i8")
PACKED = "packed"
GYRO_LAYOUT_DTYPES = {"t": "<f8", "rate": "<f4"}

assert not any(a != b and b.startswith(a) for a in TOPICS for b in TOPICS), "a topic prefixes another"


class TransportError(ThermodError):
    """The ZeroMQ endpoint could not be bound/connected, or a key file is unusable."""


# ----------------------------------------------------------------------------------------- helpers
def _jsonable(x):
    """Plain JSON types; non-finite floats become null so non-Python parsers accept the header."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        x = float(x)
        return x if math.isfinite(x) else None
    if x is None or isinstance(x, str):
        return x
    if hasattr(x, "as_dict"):
        return _jsonable(x.as_dict())
    raise TypeError(f"header value of type {type(x).__name__} is not JSON-serialisable")


def _load_keypair(path, what: str) -> tuple[bytes, bytes]:
    try:
        public, secret = zmq.auth.load_certificate(os.fspath(path))
    except (OSError, ValueError) as e:
        raise TransportError(f"{what} {path}: cannot read CURVE certificate ({e}); make one with "
                             "zmq.auth.create_certificates(dir, name)") from None
    if secret is None:
        raise TransportError(f"{what} {path}: has no secret key; pass the '.key_secret' file")
    return public, secret


def _load_public_key(key) -> bytes:
    """A z85 public key given as bytes/str (40 chars) or as a path to a certificate file."""
    if isinstance(key, bytes) and len(key) == 40:
        return key
    if isinstance(key, str) and len(key) == 40 and not Path(key).exists():
        return key.encode("ascii")
    try:
        public, _ = zmq.auth.load_certificate(os.fspath(key))
    except (OSError, ValueError) as e:
        raise TransportError(f"CURVE server key {key}: expected a 40-character z85 key or a certificate "
                             f"file ({e})") from None
    return public


# --------------------------------------------------------------------------------------- publisher
class Publisher:
    """Wire-v1 PUB socket owned by one background thread.

    Parameters
    ----------
    endpoint : str
        ZeroMQ bind address; ``tcp://127.0.0.1:*`` picks a free port (see `.endpoint` after `start`).
    hwm : int
        Send high-water mark per subscriber, in messages; beyond it ZeroMQ drops (PUB never blocks).
    curve_secret_key_file : path, optional
        Server certificate (``*.key_secret``) → CURVE encryption.
    authorized_keys_dir : path, optional
        Directory of client public certificates (``*.key``); only those clients are admitted.
        Without it, any CURVE client is admitted (encryption only).
    queue_size, queue_bytes : int
        Bounds on the messages waiting for the sender thread (count, payload bytes); beyond either
        the OLDEST are dropped and counted. Gyro batches are many and small, frames few and large.
    gyro_batch_s : float
        Consecutive gyro batches are coalesced into one message for up to this long (0: one
        message per `publish_gyro` call). See `publish_gyro`.
    linger_s : float
        How long `stop` waits for queued messages to leave.
    context : zmq.Context, optional
        Share a context (needed for ``inproc://`` endpoints); by default the publisher owns one.

    `publish*` may be called from any thread and never block: they stamp ``v``, ``seq`` (per topic,
    consecutive in call order, so a queue drop shows up as a gap), ``shape`` and ``dtype`` and queue
    the message; the sender thread adds ``published`` (host monotonic at send), serialises the header
    and sends the payload without copying. Arrays are copied unless ``copy=False``, which hands
    ownership over: the caller must never write to that array again.
    """

    def __init__(self, endpoint: str = DEFAULT_ENDPOINT, *, hwm: int = 64, curve_secret_key_file=None,
                 authorized_keys_dir=None, queue_size: int = 1024, queue_bytes: int = 64 << 20,
                 gyro_batch_s: float = 0.01, linger_s: float = 0.5, context: zmq.Context | None = None):
        if queue_size < 1 or hwm < 1:
            raise ValueError("queue_size and hwm must be at least 1")
        self.endpoint = endpoint
        self.hwm, self.queue_size, self.linger_s = int(hwm), int(queue_size), float(linger_s)
        self.queue_bytes = int(queue_bytes)
        self.gyro_batch_s = float(gyro_batch_s)
        self._gyro: dict | None = None
        self._gyro_lock = threading.Lock()
        self._shared_ctx = context
        self._keys = None
        if curve_secret_key_file is not None:
            self._keys = _load_keypair(curve_secret_key_file, "curve_secret_key_file")
        if authorized_keys_dir is not None:
            if self._keys is None:
                raise TransportError("authorized_keys_dir needs curve_secret_key_file (client "
                                     "authentication runs inside the CURVE handshake)")
            if not Path(authorized_keys_dir).is_dir():
                raise TransportError(f"authorized_keys_dir {authorized_keys_dir}: not a directory")
        self.authorized_keys_dir = authorized_keys_dir
        self.public_key = self._keys[0] if self._keys else None
        self._queue: collections.deque = collections.deque()
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self._seq = dict.fromkeys(TOPICS, 0)
        self._queued = dict.fromkeys(TOPICS, 0)
        self._sent = dict.fromkeys(TOPICS, 0)
        self._queue_dropped = 0
        self._queue_nbytes = 0
        self._send_errors = 0
        self._bytes_sent = 0

    # ------------------------------------------------------------------ lifecycle
    def start(self, timeout: float = 5.0) -> Publisher:
        """Bind (in the sender thread) and return once bound; raise `TransportError` if it cannot."""
        if self._thread is not None:
            return self
        self._stopping.clear()
        ready, failure = threading.Event(), []
        self._thread = threading.Thread(target=self._run, args=(ready, failure), name="thermod-publish",
                                        daemon=True)
        self._thread.start()
        if not ready.wait(timeout):
            raise TransportError(f"{self.endpoint}: publisher thread did not bind within {timeout} s")
        if failure:
            self._thread.join()
            self._thread = None
            raise failure[0]
        return self

    def stop(self) -> None:
        """Flush what is queued (for up to `linger_s`), close the socket and end the thread."""
        if self._thread is None:
            return
        self._stopping.set()
        self._wake.set()
        self._thread.join()
        self._thread = None

    def __enter__(self) -> Publisher:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    # ------------------------------------------------------------------- publish
    def publish(self, topic: str, header: dict, array: np.ndarray | None = None, *, copy: bool = True) -> int:
        """Queue one message; returns its ``seq``. Never blocks.

        ``header`` must hold ``t`` (s, host monotonic); ``v``, ``seq``, ``shape``, ``dtype`` are set here
        (``deblurred`` defaults to false). ``array`` None means an empty payload (``shape`` [0]).
        """
        if topic not in TOPICS:
            raise ValueError(f"unknown topic {topic!r}; wire v1 topics are {TOPICS}")
        if "t" not in header:
            raise ValueError("header needs 't' (frame time, s, host monotonic)")
        if array is None:
            array = np.empty(0, np.uint8)
        dtype = array.dtype.newbyteorder("<") if array.dtype.byteorder == ">" else array.dtype
        if dtype.str not in ARRAY_DTYPES:
            raise ValueError(f"payload dtype {array.dtype} not allowed on the wire (allowed: {ARRAY_DTYPES})")
        if copy or not array.flags.c_contiguous or array.dtype != dtype:
            array = np.array(array, dtype=dtype, order="C", copy=True)
        head = dict(header)
        head.setdefault("deblurred", False)
        head.update(shape=list(array.shape), dtype=dtype.str)
        return self._enqueue(topic, head, array)

    def _enqueue(self, topic: str, head: dict, payload) -> int:
        nbytes = _nbytes(payload)
        with self._lock:
            seq = self._seq[topic]
            self._seq[topic] = seq + 1
            head["v"], head["seq"] = WIRE_VERSION, seq
            while self._queue and (len(self._queue) >= self.queue_size
                                   or self._queue_nbytes + nbytes > self.queue_bytes):
                self._queue_nbytes -= _nbytes(self._queue.popleft()[2])
                self._queue_dropped += 1
            self._queue.append((topic, head, payload))
            self._queue_nbytes += nbytes
            self._queued[topic] += 1
        self._wake.set()
        return seq

    def publish_frame(self, image: np.ndarray, t: float, *, frame_id: int, deblurred: bool,
                      kernel_size=None, kernel_extent_px: float | None = None, coverage: float | None = None,
                      reason: str | None = None, copy: bool = True, **extra) -> int:
        """A deblurred (or passed-through) float32 frame.

        ``kernel_size`` is the blur kernel's [kh, kw]; ``coverage`` the fraction of the 5τ kernel
        weight (Eq. 18) covered by gyro samples; ``reason`` says why the frame was not deblurred.
        """
        image = np.asarray(image)
        if image.ndim != 2:
            raise ValueError(f"frame image must be 2-D [H, W], got shape {image.shape}")
        if image.dtype != np.float32:
            image, copy = image.astype(np.float32), False
        header = dict(extra, t=float(t), frame_id=int(frame_id), deblurred=bool(deblurred),
                      kernel_size=None if kernel_size is None else [int(s) for s in kernel_size],
                      kernel_extent_px=kernel_extent_px, coverage=coverage,
                      reason=None if deblurred else (reason or "unspecified"))
        return self.publish("frame", header, image, copy=copy)

    def publish_raw(self, image: np.ndarray, t: float, *, frame_id: int, copy: bool = True, **extra) -> int:
        """A camera frame as received (uint16 counts)."""
        image = np.asarray(image)
        if image.ndim != 2 or image.dtype != np.uint16:
            raise ValueError(f"raw image must be uint16 [H, W], got {image.dtype} {image.shape}")
        header = dict(extra, t=float(t), frame_id=int(frame_id), deblurred=False)
        return self.publish("raw", header, image, copy=copy)

    def publish_gyro(self, t: np.ndarray, rate: np.ndarray, *, seq: int, gap_before: bool = False,
                     n_lost: int = 0, **extra) -> int | None:
        """A batch of raw gyro samples (gyro clock mapped to host time, gyro frame, rad/s).

        Payload: ``t`` as <f8 [N] followed by ``rate`` as <f4 [N, 3] (header ``layout``). ``seq`` is the
        device index of the first sample and goes into ``sample_seq`` (the header's ``seq`` is the
        message counter, as on every topic). Consecutive batches (contiguous ``seq``, no gap) are
        coalesced for up to ``gyro_batch_s``: drivers deliver a few samples every millisecond or two,
        and hundreds of tiny messages a second would fill subscribers' HWMs. Returns the message's
        ``seq`` when this call queued one, else None (the samples wait for the next message).
        """
        t = np.array(t, dtype="<f8").ravel()
        rate = np.array(rate, dtype="<f4")
        n = len(t)
        if rate.shape != (n, 3):
            raise ValueError(f"gyro rate must be [{n}, 3] to match t, got {rate.shape}")
        if n == 0:
            raise ValueError("empty gyro batch")
        now = time.monotonic()
        with self._gyro_lock:
            p = self._gyro
            out = None
            if p is not None and (gap_before or int(seq) != p["seq"] + p["n"] or extra != p["extra"]):
                out = self._flush_gyro_locked()
                p = None
            if p is None:
                self._gyro = p = {"t": [], "rate": [], "seq": int(seq), "n": 0, "since": now,
                                  "gap_before": bool(gap_before), "n_lost": int(n_lost), "extra": extra}
            p["t"].append(t)
            p["rate"].append(rate)
            p["n"] += n
            if now - p["since"] >= self.gyro_batch_s or p["n"] >= 4096:
                out = self._flush_gyro_locked()
        if self._gyro is not None:
            self._wake.set()  # the sender thread flushes it if no batch follows in time
        return out

    def _flush_gyro_locked(self, older_than: float | None = None) -> int | None:
        p = self._gyro
        if p is None or (older_than is not None and time.monotonic() - p["since"] < older_than):
            return None
        self._gyro = None
        t = np.concatenate(p["t"]) if len(p["t"]) > 1 else p["t"][0]
        rate = np.concatenate(p["rate"]) if len(p["rate"]) > 1 else p["rate"][0]
        n = p["n"]
        header = dict(p["extra"], t=float(t[-1]), deblurred=False, shape=[n], dtype=PACKED, n=n,
                      layout=[["t", "<f8", [n]], ["rate", "<f4", [n, 3]]], sample_seq=p["seq"],
                      gap_before=p["gap_before"], n_lost=p["n_lost"])
        return self._enqueue("gyro", header, t.tobytes() + rate.tobytes())

    def flush_gyro(self) -> int | None:
        """Queue the coalesced gyro samples now (also done by `stop` and after ``gyro_batch_s``)."""
        with self._gyro_lock:
            return self._flush_gyro_locked()

    def publish_health(self, *, rates: dict | None = None, drops: dict | None = None,
                       devices: dict | None = None, calibration=None, t: float | None = None, **extra) -> int:
        """Daemon health: rates (Hz), drop counters, device states, and the calibration in use
        (a `Calibration` or its `as_dict()`, recording attribute names) so `record` can write it."""
        header = dict(extra, t=time.monotonic() if t is None else float(t), deblurred=False,
                      rates=rates or {}, drops=drops or {}, devices=devices or {},
                      calibration=None if calibration is None else _jsonable(calibration))
        return self.publish("health", header, None)

    def stats(self) -> dict:
        with self._lock:
            return {"endpoint": self.endpoint, "running": self.running, "queued": dict(self._queued),
                    "sent": dict(self._sent), "queue_depth": len(self._queue),
                    "queue_bytes": self._queue_nbytes,
                    "queue_dropped": self._queue_dropped, "send_errors": self._send_errors,
                    "bytes_sent": self._bytes_sent}

    # -------------------------------------------------------------- sender thread
    def _run(self, ready: threading.Event, failure: list) -> None:
        ctx = self._shared_ctx or zmq.Context()
        auth = sock = None
        try:
            try:
                if self.authorized_keys_dir is not None:
                    auth = ThreadAuthenticator(ctx, log=log.getChild("auth"))
                    auth.start()
                    auth.configure_curve(domain="*", location=os.fspath(self.authorized_keys_dir))
                sock = ctx.socket(zmq.PUB)
                sock.setsockopt(zmq.SNDHWM, self.hwm)
                sock.setsockopt(zmq.LINGER, int(self.linger_s * 1000))
                if self._keys is not None:
                    sock.curve_server = True
                    sock.curve_publickey, sock.curve_secretkey = self._keys
                sock.bind(self.endpoint)
                self.endpoint = sock.getsockopt_string(zmq.LAST_ENDPOINT)
            except zmq.ZMQError as e:
                failure.append(TransportError(f"cannot bind publisher to {self.endpoint}: {e}"))
                return
            finally:
                ready.set()
            log.info("publishing wire v%d on %s%s", WIRE_VERSION, self.endpoint,
                     " (CURVE)" if self._keys else "")
            while True:
                self._wake.wait(0.2 if self._gyro is None else max(self.gyro_batch_s, 1e-3))
                self._wake.clear()
                stopping = self._stopping.is_set()
                with self._gyro_lock:
                    self._flush_gyro_locked(older_than=None if stopping else self.gyro_batch_s)
                self._drain(sock)
                if stopping:
                    self._drain(sock)
                    break
        finally:
            if sock is not None:
                sock.close()
            if auth is not None:
                auth.stop()
            if self._shared_ctx is None:
                ctx.term()

    def _drain(self, sock) -> None:
        while True:
            with self._lock:
                if not self._queue:
                    return
                topic, head, payload = self._queue.popleft()
                self._queue_nbytes -= _nbytes(payload)
            head["published"] = time.monotonic()
            try:
                hbytes = json.dumps(_jsonable(head), separators=(",", ":"), allow_nan=False).encode()
            except (TypeError, ValueError) as e:
                log.error("dropping %s seq %s: header not serialisable (%s)", topic, head.get("seq"), e)
                with self._lock:
                    self._send_errors += 1
                continue
            try:
                # PUB never blocks: above the HWM ZeroMQ drops for that subscriber; the payload's
                # buffer now belongs to ZeroMQ, which is why publish() copied it or took ownership.
                sock.send_multipart([topic.encode(), hbytes, payload], flags=zmq.NOBLOCK, copy=False)
            except zmq.ZMQError as e:
                log.warning("send of %s seq %s failed: %s", topic, head.get("seq"), e)
                with self._lock:
                    self._send_errors += 1
                continue
            with self._lock:
                self._sent[topic] += 1
                self._bytes_sent += len(hbytes) + _nbytes(payload)


def _nbytes(payload) -> int:
    return payload.nbytes if isinstance(payload, np.ndarray) else len(payload)


# -------------------------------------------------------------------------------------- subscriber
class MessageError(ValueError):
    """A received message violates wire v1 (counted by `kind` and logged by `Subscriber`, never raised
    out of it). `kind`: framing, topic, header_size, json, version, header, dtype, shape, layout,
    payload_size."""

    def __init__(self, kind: str, message: str):
        self.kind = kind
        super().__init__(message)


def decode(frames: list, *, max_header_bytes: int = 65536, topics: Iterable[str] = TOPICS):
    """Validate and decode one received multipart message → (topic, header, array).

    ``frames`` are bytes or `zmq.Frame` objects. Raises `MessageError` naming what is wrong.
    The array is a read-only view on the payload (no copy); ``gyro`` decodes to a structured array
    with fields ``t`` (<f8) and ``rate`` (<f4, 3); ``health`` to an empty uint8 array.
    """
    if len(frames) != 3:
        raise MessageError("framing", f"expected 3 frames [topic, header, payload], got {len(frames)}")
    raw_topic, raw_header, payload = (f.buffer if isinstance(f, zmq.Frame) else memoryview(f) for f in frames)
    topic = bytes(raw_topic).decode("ascii", "replace")
    if topic not in topics:
        raise MessageError("topic", f"topic {topic!r} is not one of {tuple(topics)}")
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
    if dtype not in ARRAY_DTYPES:
        raise MessageError("dtype", f"{topic}: dtype {dtype!r} not allowed (expected one of {ARRAY_DTYPES})")
    need = math.prod(shape) * np.dtype(dtype).itemsize
    if need != payload.nbytes:
        raise MessageError("payload_size", f"{topic}: payload is {payload.nbytes} bytes, shape {shape} × "
                                           f"{dtype} needs {need}")
    if topic in ("frame", "raw") and len(shape) != 2:
        raise MessageError("shape", f"{topic}: shape must be [H, W], got {shape}")
    array = np.frombuffer(payload, dtype=dtype).reshape(shape)
    array.flags.writeable = False  # a view on ZeroMQ's message buffer
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
        if GYRO_LAYOUT_DTYPES.get(name) != dt:
            raise MessageError("layout", f"{topic}: layout entry {name!r} must have dtype "
                                         f"{GYRO_LAYOUT_DTYPES.get(name)!r}, got {dt!r}")
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
    out = np.empty(n, dtype=[("t", "<f8"), ("rate", "<f4", (3,))])
    out["t"], out["rate"] = parts["t"], parts["rate"]
    out.flags.writeable = False
    return out


def _reject_constant(name):
    raise ValueError(f"non-standard JSON constant {name}")


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _shape(topic, key, shape) -> list:
    if not (isinstance(shape, list) and len(shape) <= 4
            and all(isinstance(s, int) and not isinstance(s, bool) and 0 <= s < 2**31 for s in shape)):
        raise MessageError("shape", f"{topic}: header {key!r} must be a list of ≤ 4 non-negative ints, "
                                    f"got {shape!r}")
    return shape


class Subscriber:
    """Wire-v1 SUB client: validated ``(topic, header, array)`` messages, seq gaps counted per topic.

    Parameters
    ----------
    endpoint : str
        The publisher's address.
    topics : iterable of str
        Exact topics to receive (ZeroMQ matches prefixes; `recv` also checks equality).
    curve_server_key : bytes | str | path, optional
        The publisher's public key (z85) or its certificate file → CURVE.
    curve_client_key_file : path, optional
        This client's certificate (``*.key_secret``); a throwaway key pair is made if omitted.
    max_header_bytes : int
        Larger headers are rejected.
    context : zmq.Context, optional
        Share a context (needed for ``inproc://`` endpoints); by default the subscriber owns one.
    rcvhwm : int
        Receive high-water mark, in messages (ZeroMQ's default, 1000): beyond it messages are dropped
        and show up in `gaps`. Gyro batches are small but frequent, so do not set it too low.

    Attributes: ``gaps`` (topic → messages lost, from seq jumps), ``received``, ``errors``
    (`MessageError.kind` → count of rejected messages), ``restarts`` (seq went backwards: the
    publisher restarted). Each returned header gains ``received`` (host monotonic at receipt).
    Like any ZeroMQ socket, a Subscriber belongs to one thread.
    """

    def __init__(self, endpoint: str = DEFAULT_ENDPOINT, topics: Iterable[str] = ("frame",), *,
                 curve_server_key=None, curve_client_key_file=None, max_header_bytes: int = 65536,
                 rcvhwm: int = 1000, context: zmq.Context | None = None):
        self.topics = tuple(topics)
        unknown = [t for t in self.topics if t not in TOPICS]
        if unknown or not self.topics:
            raise ValueError(f"topics must be a non-empty subset of {TOPICS}, got {self.topics}")
        self.endpoint, self.max_header_bytes = endpoint, int(max_header_bytes)
        self.gaps = collections.Counter()
        self.received = collections.Counter()
        self.restarts = collections.Counter()
        self.errors = collections.Counter()
        self._last_seq: dict[str, int] = {}
        self._own_ctx = context is None
        self._ctx = zmq.Context() if context is None else context
        self._sock = self._ctx.socket(zmq.SUB)
        try:
            self._sock.setsockopt(zmq.RCVHWM, int(rcvhwm))
            self._sock.setsockopt(zmq.LINGER, 0)
            if curve_server_key is not None:
                self._sock.curve_serverkey = _load_public_key(curve_server_key)
                if curve_client_key_file is not None:
                    public, secret = _load_keypair(curve_client_key_file, "curve_client_key_file")
                else:
                    public, secret = zmq.curve_keypair()
                self._sock.curve_publickey, self._sock.curve_secretkey = public, secret
            for t in self.topics:
                self._sock.setsockopt(zmq.SUBSCRIBE, t.encode())
            self._sock.connect(endpoint)
        except zmq.ZMQError as e:
            self.close()
            raise TransportError(f"cannot connect subscriber to {endpoint}: {e}") from None
        except TransportError:
            self.close()
            raise

    def recv(self, timeout: float | None = None):
        """Next valid message, or None after ``timeout`` seconds (None = wait forever).
        Malformed messages are counted in ``errors``, logged and skipped."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            wait_ms = 200 if deadline is None else max(0, int((deadline - time.monotonic()) * 1000))
            if not self._sock.poll(wait_ms):
                if deadline is not None and time.monotonic() >= deadline:
                    return None
                continue
            frames = self._sock.recv_multipart(copy=False)
            try:
                topic, header, array = decode(frames, max_header_bytes=self.max_header_bytes,
                                              topics=self.topics)
            except MessageError as e:
                self.errors[e.kind] += 1
                n = sum(self.errors.values())
                if n <= 10 or n % 1000 == 0:
                    log.warning("rejected message #%d from %s: %s", n, self.endpoint, e)
                continue
            header["received"] = time.monotonic()
            self._track(topic, header["seq"])
            return topic, header, array

    def _track(self, topic: str, seq: int) -> None:
        last = self._last_seq.get(topic)
        if last is not None:
            if seq > last + 1:
                self.gaps[topic] += seq - last - 1
            elif seq <= last:
                self.restarts[topic] += 1
        self._last_seq[topic] = seq
        self.received[topic] += 1

    def __iter__(self) -> Iterator:
        while True:
            msg = self.recv(None)
            if msg is not None:
                yield msg

    def close(self) -> None:
        if not self._sock.closed:
            self._sock.close(linger=0)
        if self._own_ctx:
            self._ctx.term()

    def __enter__(self) -> Subscriber:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

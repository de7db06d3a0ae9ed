"""The daemon's ZeroMQ publisher for wire format v1 (docs/wire.md); the codec is `thermod.io.wire`, the
endpoint and key rules `thermod.io.endpoints`, the subscriber `thermod.client.subscriber`.

The daemon binds one XPUB socket (a PUB that also hears what its subscribers subscribe to); every
message is three frames ``[topic, header, payload]``. `Publisher` owns that socket in one thread and
never blocks its callers. `wants(topic)` says whether any subscriber now subscribes to a topic, so
that work only a subscriber would read (packing kernels, copying raw frames, batching gyro samples) is
skipped while none does.

Security: the publisher binds loopback (or ``ipc://``) unless it has CURVE keys or is told
``allow_insecure_remote``. With ``curve_secret_key_file`` (a file written by
``zmq.auth.create_certificates``, mode 0600) it encrypts with CURVE; with ``authorized_keys_dir`` it
also admits only clients whose public keys are in that directory.

Memory: ZeroMQ keeps a send queue per subscriber. ``max_queue_bytes`` bounds the bytes of sent
messages that ZeroMQ still holds, summed over every subscriber (tracked per message); a message that
would exceed it is not sent and is counted in ``stats()["budget_dropped"]``. The per-subscriber
SNDHWM is sized so that `BUDGETED_STALLED_SUBSCRIBERS` subscriber that stops reading fits in the budget
with room to spare for the others; more stalled subscribers than that make the publisher drop (and
count) messages instead of growing, until ZMTP heartbeats (unanswered for ``stall_timeout_s``)
disconnect the stalled ones and free what they pinned.
"""

from __future__ import annotations

import collections
import logging
import os
import threading
import time
from pathlib import Path

import numpy as np
import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator

from thermod.io.endpoints import (
    DEFAULT_ENDPOINT,
    DEFAULT_HWM,
    DEFAULT_MAX_QUEUE_BYTES,
    TransportError,
    check_endpoint,
    claim_ipc,
    ipc_path,
    is_loopback,
    load_keypair,
    security_problem,
)
from thermod.io.wire import (
    TOPICS,
    WIRE_VERSION,
    array_header,
    encode_header,
    jsonable,
    nbytes,
    pack_gyro,
    pack_kernel,
    wire_array,
)

log = logging.getLogger(__name__)

# The SNDHWM leaves room in the byte budget for this many subscribers that stop reading (each pins a
# full send queue of its own messages until the heartbeat drops it); beyond them, new messages are
# dropped and counted until then.
BUDGETED_STALLED_SUBSCRIBERS = 1
DEFAULT_STALL_TIMEOUT_S = 5.0
MIN_HWM = 2


# --------------------------------------------------------------------------------------- publisher
class Publisher:
    """Wire-v1 PUB socket owned by one background thread.

    Parameters
    ----------
    endpoint : str
        ZeroMQ bind address; ``tcp://127.0.0.1:*`` picks a free port (see `.endpoint` after `start`).
        A non-loopback tcp address needs CURVE keys or ``allow_insecure_remote``.
    hwm : int
        Upper bound on the send high-water mark per subscriber, in messages; beyond it ZeroMQ drops
        for that subscriber (PUB never blocks).
    max_queue_bytes : int
        Byte budget for sent messages ZeroMQ still holds, all subscribers together; a message that
        would exceed it is dropped (counted in ``budget_dropped``; health messages always go).
    max_message_bytes : int, optional
        The largest payload this publisher will send (e.g. H×W×4 for float32 frames). With it, the
        SNDHWM becomes ``max_queue_bytes / ((BUDGETED_STALLED_SUBSCRIBERS + 1) × max_message_bytes) − 1``
        (at least 2, at most ``hwm``).
    curve_secret_key_file : path, optional
        Server certificate (``*.key_secret``, not readable by group/others) → CURVE encryption.
    authorized_keys_dir : path, optional
        Directory of client public certificates (``*.key``); only those clients are admitted.
        Without it, any CURVE client is admitted (encryption only).
    stall_timeout_s : float
        A subscriber whose connection answers no ZMTP heartbeat for this long (it stopped reading:
        its queues are full) is disconnected, releasing the messages it pinned. Needs peers with
        ZMTP 3.1 (libzmq ≥ 4.2).
    allow_insecure_remote : bool
        Permit a non-loopback bind without CURVE (logged as a warning and listed in ``stats()["warnings"]``).
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

    def __init__(self, endpoint: str = DEFAULT_ENDPOINT, *, hwm: int = DEFAULT_HWM,
                 max_queue_bytes: int = DEFAULT_MAX_QUEUE_BYTES, max_message_bytes: int | None = None,
                 curve_secret_key_file=None, authorized_keys_dir=None, allow_insecure_remote: bool = False,
                 stall_timeout_s: float = DEFAULT_STALL_TIMEOUT_S,
                 queue_size: int = 1024, queue_bytes: int = 64 << 20, gyro_batch_s: float = 0.05,
                 linger_s: float = 0.5, context: zmq.Context | None = None):
        if queue_size < 1 or hwm < 1:
            raise ValueError("queue_size and hwm must be at least 1")
        if max_queue_bytes < 1 or (max_message_bytes is not None and max_message_bytes < 1):
            raise ValueError("max_queue_bytes and max_message_bytes must be positive")
        self.endpoint = check_endpoint(endpoint)
        self.max_queue_bytes = int(max_queue_bytes)
        if not stall_timeout_s > 0:
            raise ValueError("stall_timeout_s must be positive")
        self.stall_timeout_s = float(stall_timeout_s)
        self.hwm = int(hwm)
        if max_message_bytes is not None:
            # a stalled subscriber holds SNDHWM messages plus the one its connection is writing;
            # one more share of the budget is left for messages in flight to healthy subscribers
            fit = self.max_queue_bytes // ((BUDGETED_STALLED_SUBSCRIBERS + 1) * int(max_message_bytes)) - 1
            self.hwm = max(MIN_HWM, min(self.hwm, fit))
        self.queue_size, self.linger_s = int(queue_size), float(linger_s)
        self.queue_bytes = int(queue_bytes)
        self.gyro_batch_s = float(gyro_batch_s)
        self._gyro: dict | None = None
        self._gyro_lock = threading.Lock()
        self._shared_ctx = context
        self._keys = None
        if curve_secret_key_file is not None:
            self._keys = load_keypair(curve_secret_key_file, "curve_secret_key_file")
        bad = security_problem(self.endpoint, self._keys is not None, authorized_keys_dir is not None,
                               allow_insecure_remote)
        if bad is not None:
            raise TransportError(f"publish.{bad[0]}: {bad[1]}")
        if authorized_keys_dir is not None and not Path(authorized_keys_dir).is_dir():
            raise TransportError(f"authorized_keys_dir {authorized_keys_dir}: not a directory")
        self.warnings: list[str] = []
        if self._keys is None and not is_loopback(self.endpoint):
            self.warnings.append(f"insecure_remote: {self.endpoint} is reachable from the network "
                                 "without CURVE (publish.allow_insecure_remote = true)")
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
        self._budget_dropped = dict.fromkeys(TOPICS, 0)
        self._held: list = []          # (MessageTracker, bytes) of sent payloads ZeroMQ still holds
        self._held_bytes = 0
        self._held_peak = 0
        self._queue_dropped = 0
        self._queue_nbytes = 0
        self._send_errors = 0
        self._bytes_sent = 0
        self._subscribed: frozenset[bytes] = frozenset()   # the topic prefixes subscribers ask for now

    # ------------------------------------------------------------------ lifecycle
    def start(self, timeout: float = 5.0) -> Publisher:
        """Bind (in the sender thread) and return once bound; raise `TransportError` if it cannot."""
        if self._thread is not None:
            return self
        for w in self.warnings:
            log.warning("%s", w)
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

    def wants(self, topic: str) -> bool:
        """Whether some subscriber subscribes to `topic` now (a prefix of it, ``""`` included). A new
        subscription is heard at the sender's next pass (within ``gyro_batch_s``, or 0.2 s)."""
        name = topic.encode()
        return any(name.startswith(p) for p in self._subscribed)

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
        array = wire_array(array, copy=copy)
        return self._enqueue(topic, array_header(header, array), array)

    def _enqueue(self, topic: str, head: dict, payload) -> int:
        size = nbytes(payload)
        with self._lock:
            seq = self._seq[topic]
            self._seq[topic] = seq + 1
            head["v"], head["seq"] = WIRE_VERSION, seq
            while self._queue and (len(self._queue) >= self.queue_size
                                   or self._queue_nbytes + size > self.queue_bytes):
                self._queue_nbytes -= nbytes(self._queue.popleft()[2])
                self._queue_dropped += 1
            self._queue.append((topic, head, payload))
            self._queue_nbytes += size
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

    def publish_kernel(self, kernel, t: float, *, frame_id: int, **extra) -> int:
        """The blur kernel a deblurred frame was deconvolved with (`thermod.io.wire.pack_kernel`):
        float32 [kh, kw], or [rows, cols, kh, kw] for a grid; header ``origin``, ``extent_px``,
        ``coverage``, and the frame's ``t`` and ``frame_id``. `kernel`: a Kernel, a KernelGrid, or
        one already packed (`pack_kernel`'s (fields, weights))."""
        fields, weights = kernel if isinstance(kernel, tuple) else pack_kernel(kernel)
        header = dict(extra, t=float(t), frame_id=int(frame_id), deblurred=False, **fields)
        return self.publish("kernel", header, weights)

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
            started = p is None
            if started:
                self._gyro = p = {"t": [], "rate": [], "seq": int(seq), "n": 0, "since": now,
                                  "gap_before": bool(gap_before), "n_lost": int(n_lost), "extra": extra}
            p["t"].append(t)
            p["rate"].append(rate)
            p["n"] += n
            if now - p["since"] >= self.gyro_batch_s or p["n"] >= 4096:
                out = self._flush_gyro_locked()
        if started and self._gyro is not None:
            # once a batch: the sender then waits at most gyro_batch_s, and flushes it if no call does
            # (a wake on every call cost a pass of the sender's loop per driver batch)
            self._wake.set()
        return out

    def _flush_gyro_locked(self, older_than: float | None = None) -> int | None:
        p = self._gyro
        if p is None or (older_than is not None and time.monotonic() - p["since"] < older_than):
            return None
        self._gyro = None
        t = np.concatenate(p["t"]) if len(p["t"]) > 1 else p["t"][0]
        rate = np.concatenate(p["rate"]) if len(p["rate"]) > 1 else p["rate"][0]
        fields, payload = pack_gyro(t, rate)
        header = dict(p["extra"], t=float(t[-1]), deblurred=False, **fields, sample_seq=p["seq"],
                      gap_before=p["gap_before"], n_lost=p["n_lost"])
        return self._enqueue("gyro", header, payload)

    def publish_health(self, *, rates: dict | None = None, drops: dict | None = None,
                       devices: dict | None = None, calibration=None, t: float | None = None, **extra) -> int:
        """Daemon health: rates (Hz), drop counters, device states, and the calibration in use
        (a `Calibration` or its `as_dict()`, recording attribute names) so `record` can write it."""
        header = dict(extra, t=time.monotonic() if t is None else float(t), deblurred=False,
                      rates=rates or {}, drops=drops or {}, devices=devices or {},
                      calibration=None if calibration is None else jsonable(calibration))
        return self.publish("health", header, None)

    def stats(self) -> dict:
        """Counters: ``budget_dropped`` (per topic, not sent because ZeroMQ already held
        ``max_queue_bytes``), ``held_bytes``/``held_peak_bytes`` (sent payloads ZeroMQ still holds),
        ``queue_dropped`` (oldest dropped from the hand-off queue), ``hwm`` (per subscriber),
        ``warnings`` (e.g. an insecure remote bind), ``subscribed`` (the topic prefixes subscribers ask
        for now; "" is every topic). ``held_bytes`` is read from the trackers now, not
        at the sender's last pass, so it falls to 0 as soon as ZeroMQ lets the last payload go."""
        self._release_held()
        with self._lock:
            return {"endpoint": self.endpoint, "running": self.running, "queued": dict(self._queued),
                    "sent": dict(self._sent), "queue_depth": len(self._queue),
                    "queue_bytes": self._queue_nbytes,
                    "queue_dropped": self._queue_dropped, "send_errors": self._send_errors,
                    "bytes_sent": self._bytes_sent, "hwm": self.hwm, "max_queue_bytes": self.max_queue_bytes,
                    "held_bytes": self._held_bytes, "held_peak_bytes": self._held_peak,
                    "budget_dropped": dict(self._budget_dropped),
                    "budget_dropped_total": sum(self._budget_dropped.values()),
                    "subscribed": sorted(p.decode(errors="replace") for p in self._subscribed),
                    "warnings": list(self.warnings)}

    # -------------------------------------------------------------- sender thread
    def _run(self, ready: threading.Event, failure: list) -> None:
        ctx = self._shared_ctx or zmq.Context()
        auth = sock = owned = None
        try:
            try:
                path = ipc_path(self.endpoint)
                if path is not None:
                    claim_ipc(path, "publish.endpoint")
                if self.authorized_keys_dir is not None:
                    auth = ThreadAuthenticator(ctx, log=log.getChild("auth"))
                    auth.start()
                    auth.configure_curve(domain="*", location=os.fspath(self.authorized_keys_dir))
                sock = ctx.socket(zmq.XPUB)
                sock.setsockopt(zmq.SNDHWM, self.hwm)
                # ZMTP heartbeats: a subscriber that stops reading stops answering them too, so its
                # connection (and the queue it pins) is dropped after stall_timeout_s
                sock.setsockopt(zmq.HEARTBEAT_IVL, max(1, int(self.stall_timeout_s * 1000 / 3)))
                sock.setsockopt(zmq.HEARTBEAT_TIMEOUT, max(1, int(self.stall_timeout_s * 1000)))
                sock.setsockopt(zmq.LINGER, int(self.linger_s * 1000))
                if self._keys is not None:
                    sock.curve_server = True
                    sock.curve_publickey, sock.curve_secretkey = self._keys
                sock.bind(self.endpoint)
                self.endpoint = sock.getsockopt_string(zmq.LAST_ENDPOINT)
                owned = _socket_file(ipc_path(self.endpoint))
            except zmq.ZMQError as e:
                hint = " (another process holds the port; is a second thermod running?)" \
                    if e.errno == zmq.EADDRINUSE else ""
                failure.append(TransportError(f"cannot bind publisher to publish.endpoint {self.endpoint!r}: "
                                              f"{e}{hint}"))
                return
            except TransportError as e:
                failure.append(e)
                return
            finally:
                ready.set()
            log.info("publishing wire v%d on %s%s, SNDHWM %d, queue budget %.0f MB", WIRE_VERSION,
                     self.endpoint, " (CURVE)" if self._keys else "", self.hwm, self.max_queue_bytes / 1e6)
            while True:
                self._wake.wait(0.2 if self._gyro is None else max(self.gyro_batch_s, 1e-3))
                self._wake.clear()
                stopping = self._stopping.is_set()
                with self._gyro_lock:
                    self._flush_gyro_locked(older_than=None if stopping else self.gyro_batch_s)
                sock.getsockopt(zmq.EVENTS)  # lets the socket finish closed subscribers' pipes (frees queues)
                self._hear_subscriptions(sock)
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
            _remove_socket_file(owned)

    def _hear_subscriptions(self, sock) -> None:
        """Apply the (un)subscriptions XPUB passed up: ``\\x01`` + prefix when the first subscriber asks
        for a prefix, ``\\x00`` + prefix when the last one leaves (or its connection closes)."""
        subscribed = set(self._subscribed)
        while True:
            try:
                msg = sock.recv(zmq.NOBLOCK)
            except zmq.Again:
                break
            except zmq.ZMQError as e:     # the socket closing under a stop: keep what was heard
                log.debug("subscriptions: %s", e)
                break
            if msg[:1] == b"\x01":
                subscribed.add(msg[1:])
            elif msg[:1] == b"\x00":
                subscribed.discard(msg[1:])
        self._subscribed = frozenset(subscribed)

    def _release_held(self) -> None:
        """Forget the payloads ZeroMQ has let go of (every subscriber's queue sent or dropped them).
        Called by the sender and by `stats`, so under the lock the sender appends under."""
        with self._lock:
            self._held = [(tr, n) for tr, n in self._held if not tr.done]
            self._held_bytes = sum(n for _, n in self._held)

    def _drain(self, sock) -> None:
        self._release_held()
        while True:
            with self._lock:
                if not self._queue:
                    return
                topic, head, payload = self._queue.popleft()
                self._queue_nbytes -= nbytes(payload)
            size = nbytes(payload)
            if topic != "health" and self._held_bytes + size > self.max_queue_bytes:
                self._release_held()
                if self._held_bytes + size > self.max_queue_bytes:
                    with self._lock:
                        self._budget_dropped[topic] += 1
                    continue
            head["published"] = time.monotonic()
            try:
                hbytes = encode_header(head)
            except (TypeError, ValueError) as e:
                log.error("dropping %s seq %s: header not serialisable (%s)", topic, head.get("seq"), e)
                with self._lock:
                    self._send_errors += 1
                continue
            try:
                # PUB never blocks: above the HWM ZeroMQ drops for that subscriber; the payload's
                # buffer now belongs to ZeroMQ, which is why publish() copied it or took ownership.
                tracker = sock.send_multipart([topic.encode(), hbytes, payload], flags=zmq.NOBLOCK,
                                              copy=False, track=True)
            except zmq.ZMQError as e:
                log.warning("send of %s seq %s failed: %s", topic, head.get("seq"), e)
                with self._lock:
                    self._send_errors += 1
                continue
            with self._lock:
                self._sent[topic] += 1
                self._bytes_sent += len(hbytes) + size
                if not tracker.done:
                    self._held.append((tracker, size))
                    self._held_bytes += size
                    self._held_peak = max(self._held_peak, self._held_bytes)


def _socket_file(path: str | None) -> tuple[str, int, int] | None:
    """(path, device, inode) of the ``ipc://`` socket file just bound, to remove it on close."""
    if path is None:
        return None
    try:
        st = os.stat(path)
    except OSError:
        return None
    return path, st.st_dev, st.st_ino


def _remove_socket_file(owned: tuple[str, int, int] | None) -> None:
    """ZeroMQ leaves an ``ipc://`` socket file behind on close; remove it, unless the file at that path
    is no longer the one this publisher bound (another daemon took over the path)."""
    if owned is None:
        return
    path, dev, ino = owned
    try:
        st = os.stat(path)
        if (st.st_dev, st.st_ino) == (dev, ino):
            os.unlink(path)
    except OSError:
        pass

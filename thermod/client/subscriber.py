"""The wire-v1 subscriber: what a client of the daemon (`thermod watch`, `thermod record`, your code)
reads the stream with. Every message is validated (`thermod.io.wire.decode`); sequence gaps are counted.

Example (a subscriber on the same host)::

    from thermod.client.subscriber import Subscriber

    with Subscriber("tcp://127.0.0.1:5555", topics=("frame", "health")) as sub:
        for topic, header, array in sub:          # array is read-only, owned by the message
            if topic == "frame":
                print(header["frame_id"], header["deblurred"], array.shape, array.dtype)
            print("lost so far:", sub.gaps)
"""

from __future__ import annotations

import collections
import logging
import math
import time
from collections.abc import Iterable, Iterator

import zmq

from thermod.io.endpoints import (
    DEFAULT_ENDPOINT,
    TransportError,
    check_endpoint,
    listening,
    load_keypair,
    load_public_key,
)
from thermod.io.wire import MAX_HEADER_BYTES, MAX_PAYLOAD_BYTES, TOPICS, MessageError, decode

log = logging.getLogger(__name__)

SILENCE_S = 4.0          # the daemon publishes health every second: four missed in a row


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
    max_message_bytes : int
        The largest frame (payload) this subscriber expects, default a 4096 × 4096 float32 image.
        Set as ZMQ_MAXMSGSIZE: a publisher that announces a larger frame is disconnected on its
        size prefix, before the frame's bytes are received.
    context : zmq.Context, optional
        Share a context (needed for ``inproc://`` endpoints); by default the subscriber owns one.
    rcvhwm : int
        Receive high-water mark, in messages (ZeroMQ's default, 1000): beyond it messages are dropped
        and show up in `gaps`. Gyro batches are small but frequent, so do not set it too low.

    Attributes: ``gaps`` (topic → messages lost, from seq jumps), ``received``, ``first_seq`` and
    ``last_seq`` (topic → seq of the first and latest message; with no restart, ``received + gaps``
    equals ``last_seq − first_seq + 1``), ``errors``
    (`MessageError.kind` → count of rejected messages), ``disconnects`` (connections dropped, e.g. by a
    frame above ``max_message_bytes``; each is redialled), ``restarts`` (seq went backwards: the
    publisher restarted). Each returned header gains ``received`` (host monotonic at receipt).
    Like any ZeroMQ socket, a Subscriber belongs to one thread.
    """

    def __init__(self, endpoint: str = DEFAULT_ENDPOINT, topics: Iterable[str] = ("frame",), *,
                 curve_server_key=None, curve_client_key_file=None, max_header_bytes: int = MAX_HEADER_BYTES,
                 max_message_bytes: int = MAX_PAYLOAD_BYTES, rcvhwm: int = 1000,
                 context: zmq.Context | None = None):
        check_endpoint(endpoint, "subscriber endpoint")
        self.topics = tuple(topics)
        unknown = [t for t in self.topics if t not in TOPICS]
        if unknown or not self.topics:
            raise ValueError(f"topics must be a non-empty subset of {TOPICS}, got {self.topics}")
        self.endpoint, self.max_header_bytes = endpoint, int(max_header_bytes)
        if max_message_bytes < 1:
            raise ValueError("max_message_bytes must be positive")
        self.max_message_bytes = int(max_message_bytes)
        self.gaps = collections.Counter()
        self.received = collections.Counter()
        self.restarts = collections.Counter()
        self.errors = collections.Counter()
        self.first_seq: dict[str, int] = {}
        self.last_seq: dict[str, int] = {}
        self._own_ctx = context is None
        self._ctx = zmq.Context() if context is None else context
        self._sock = self._ctx.socket(zmq.SUB)
        self._monitor = None
        self._poller = zmq.Poller()
        self.disconnects = 0
        self._redial_pending = False
        try:
            self._sock.setsockopt(zmq.RCVHWM, int(rcvhwm))
            # checked per frame against its size prefix; the header is bounded by max_header_bytes
            self._sock.setsockopt(zmq.MAXMSGSIZE, max(self.max_message_bytes, self.max_header_bytes))
            self._sock.setsockopt(zmq.LINGER, 0)
            if curve_server_key is not None:
                self._sock.curve_serverkey = load_public_key(curve_server_key)
                if curve_client_key_file is not None:
                    public, secret = load_keypair(curve_client_key_file, "curve_client_key_file")
                else:
                    public, secret = zmq.curve_keypair()
                self._sock.curve_publickey, self._sock.curve_secretkey = public, secret
            for t in self.topics:
                self._sock.setsockopt(zmq.SUBSCRIBE, t.encode())
            self._sock.connect(endpoint)
            self._monitor = self._sock.get_monitor_socket(zmq.EVENT_DISCONNECTED)
            self._poller.register(self._sock, zmq.POLLIN)
            self._poller.register(self._monitor, zmq.POLLIN)
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
            ready = dict(self._poller.poll(wait_ms))
            if self._monitor in ready:
                self._count_disconnects()
            if self._sock not in ready:
                if self._redial_pending:  # only when idle: libzmq aborts if a pipe goes mid-message
                    self._redial()
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

    def _count_disconnects(self) -> None:
        while self._monitor.poll(0):
            self._monitor.recv_multipart()
            self.disconnects += 1
            self._redial_pending = True

    def _redial(self) -> None:
        """The connection dropped. ZeroMQ retries by itself after a network fault, but not after a
        protocol error such as a frame above MAXMSGSIZE; dial again in both cases, replacing its
        retry so that exactly one connection remains."""
        self._redial_pending = False
        if self.disconnects <= 10 or self.disconnects % 1000 == 0:
            log.warning("connection to %s dropped (#%d: a frame above max_message_bytes=%d, or the "
                        "publisher went away); reconnecting", self.endpoint, self.disconnects,
                        self.max_message_bytes)
        try:
            self._sock.disconnect(self.endpoint)
        except zmq.ZMQError:
            pass  # already gone
        self._sock.connect(self.endpoint)

    def _track(self, topic: str, seq: int) -> None:
        last = self.last_seq.get(topic)
        if last is None:
            self.first_seq[topic] = seq
        else:
            if seq > last + 1:
                self.gaps[topic] += seq - last - 1
            elif seq <= last:
                self.restarts[topic] += 1
        self.last_seq[topic] = seq
        self.received[topic] += 1

    def __iter__(self) -> Iterator:
        while True:
            msg = self.recv(None)
            if msg is not None:
                yield msg

    def close(self) -> None:
        if self._monitor is not None and not self._sock.closed:
            self._sock.disable_monitor()
            self._monitor.close(linger=0)
            self._monitor = None
        if not self._sock.closed:
            self._sock.close(linger=0)
        if self._own_ctx:
            self._ctx.term()

    def __enter__(self) -> Subscriber:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Silence:
    """Tells a publisher that is gone from one that is quiet, for a client that would otherwise wait
    forever (`thermod watch`, `thermod record`): after `timeout` s (0: never) with nothing received it
    checks `endpoint` (`endpoints.listening`). Nothing listening there: gone. A bound but silent
    publisher (a daemon still warming up) is waited for, `timeout` s at a time.

    Call `heard` at each message and `gone` when a receive came back empty; `due` (host monotonic) is
    when the next check is, for the receive's wait."""

    OPTION_HELP = ("when nothing arrives for this many seconds, check the endpoint and give up (exit 1) "
                   "if nothing listens there (0: never; default %(default)s: the daemon publishes health "
                   "every second)")

    def __init__(self, endpoint: str, timeout: float = SILENCE_S):
        self.endpoint, self.timeout = endpoint, timeout
        self.last = self.due = 0.0
        self.listening: bool | None = None     # after a check: whether something listened at the endpoint
        self.silent_s: float | None = None     # once gone: how long nothing had arrived
        self.heard()

    def heard(self) -> None:
        """A message arrived."""
        self.last = time.monotonic()
        self.due = self.last + self.timeout if self.timeout > 0 else math.inf

    def gone(self) -> bool:
        """After an empty receive: whether the publisher is gone (``silent_s`` then set)."""
        now = time.monotonic()
        if now < self.due:
            return False
        self.listening = listening(self.endpoint)
        if self.listening is False:
            self.silent_s = now - self.last
            return True
        self.due = time.monotonic() + self.timeout
        return False


def gone_message(command: str, endpoint: str, silent_s: float, received: bool) -> str:
    """The line `command` ends with once `Silence.gone`: `received` says whether anything came before."""
    what = "the daemon went away" if received else "nothing arrived"
    return (f"thermod {command}: {what} from {endpoint} for {silent_s:.1f} s and nothing listens there; "
            "is `thermod run` up and publishing there? (--timeout 0 waits forever)")

"""Wire v1 over real ZeroMQ sockets on loopback: round trips, validation, seq gaps, HWM drops, CURVE."""

import json
import time
from pathlib import Path

import numpy as np
import pytest
import zmq
import zmq.auth

from thermod.chaos import FROZEN_SUBSCRIBER
from thermod.client.subscriber import Subscriber
from thermod.errors import ConfigError, ThermodError
from thermod.io.endpoints import TransportError, is_loopback
from thermod.io.wire import MessageError, decode
from thermod.runtime import config
from thermod.runtime.publish import BUDGETED_STALLED_SUBSCRIBERS, Publisher

EP = "tcp://127.0.0.1:*"


def connect(pub, topics, **kw):
    """A subscriber that is provably connected: ZeroMQ drops messages sent before the subscription
    arrives (slow joiner), so warm up with health messages until one gets through."""
    sub = Subscriber(pub.endpoint, topics=(*topics, "health"), **kw)
    deadline = time.monotonic() + 30      # a hang bound: loaded machines are slow, not stuck
    while time.monotonic() < deadline:
        pub.publish_health()
        if sub.recv(0.05) is not None:
            while sub.recv(0.05) is not None:  # drain the other warm-up messages
                pass
            return sub
    sub.close()
    raise AssertionError("subscriber never connected")


@pytest.fixture
def pub():
    p = Publisher(EP, queue_size=1024, hwm=1000).start()
    yield p
    p.stop()


def test_round_trip_all_topics(pub):
    sub = connect(pub, ("frame", "raw", "gyro"))
    rng = np.random.default_rng(1)
    img = rng.normal(1000, 50, (48, 64)).astype(np.float32)
    raw = rng.integers(0, 65535, (48, 64), dtype=np.uint16)
    gt = 100.0 + np.arange(7) * 1e-3
    gr = rng.normal(0, 0.5, (7, 3)).astype(np.float32)
    t0 = time.monotonic()
    assert pub.publish_raw(raw, 12.25, frame_id=7) == 0
    assert pub.publish_frame(img, 12.25, frame_id=7, deblurred=True, kernel_size=(9, 11),
                             kernel_extent_px=4.5, coverage=0.99) == 0
    assert pub.publish_frame(img, 12.27, frame_id=8, deblurred=False, reason="gyro gap") == 1
    pub.publish_gyro(gt, gr, seq=4242, gap_before=True, n_lost=3)  # coalesced for ≤ 10 ms, then sent
    got = [sub.recv(2.0) for _ in range(4)]
    assert all(m is not None for m in got)
    by = {}
    for topic, header, array in got:
        by.setdefault(topic, []).append((header, array))

    (h, a), = by["raw"]
    assert a.dtype == np.uint16 and a.shape == (48, 64) and np.array_equal(a, raw)
    assert h["v"] == 1 and h["seq"] == 0 and h["t"] == 12.25 and h["frame_id"] == 7
    assert h["shape"] == [48, 64] and h["dtype"] == "<u2" and h["deblurred"] is False
    assert t0 <= h["published"] <= h["received"] <= time.monotonic()

    (h0, a0), (h1, a1) = by["frame"]
    assert a0.dtype == np.float32 and np.array_equal(a0, img) and not a0.flags.writeable
    assert h0["deblurred"] is True and h0["reason"] is None and h0["kernel_size"] == [9, 11]
    assert h0["coverage"] == 0.99 and h0["kernel_extent_px"] == 4.5 and h0["dtype"] == "<f4"
    assert h1["deblurred"] is False and h1["reason"] == "gyro gap" and [h0["seq"], h1["seq"]] == [0, 1]

    (h, a), = by["gyro"]
    assert h["seq"] == 0 and h["n"] == 7 and h["sample_seq"] == 4242
    assert h["gap_before"] is True and h["n_lost"] == 3
    assert h["t"] == gt[-1] and h["layout"] == [["t", "<f8", [7]], ["rate", "<f4", [7, 3]]]
    assert np.array_equal(a["t"], gt) and np.array_equal(a["rate"], gr) and a["rate"].dtype == np.float32
    assert sum(sub.gaps.values()) == 0 and sum(sub.errors.values()) == 0
    st = pub.stats()
    assert st["sent"]["frame"] == 2 and st["queue_dropped"] == 0 and st["send_errors"] == 0
    sub.close()


def test_health_carries_calibration_and_rates(pub):
    from thermod.physics.calibration import Calibration

    sub = connect(pub, ())
    cal = Calibration(width=320, height=256, tau_s=0.011, bias_rad_s=(0.01, -0.02, 0.0))
    pub.publish_health(rates={"frame_hz": 49.9, "gyro_hz": 1000.2}, drops={"frames": 2},
                       devices={"gyro": "ok", "camera": "stalled"}, calibration=cal,
                       pipeline={"latency_ms": float("nan")})
    topic, h, a = sub.recv(2.0)
    assert topic == "health" and a.size == 0 and h["shape"] == [0]
    assert h["rates"]["gyro_hz"] == 1000.2 and h["drops"] == {"frames": 2}
    assert h["devices"]["camera"] == "stalled"
    assert h["pipeline"]["latency_ms"] is None  # NaN goes out as null: strict JSON for other languages
    assert Calibration.from_dict(h["calibration"]) == cal
    sub.close()


def test_copy_protects_the_callers_buffer(pub):
    sub = connect(pub, ("frame",))
    img = np.full((8, 8), 5.0, np.float32)
    pub.publish_frame(img, 1.0, frame_id=1, deblurred=True)
    img[:] = -1.0  # the caller reuses its buffer right away
    _, _, a = sub.recv(2.0)
    assert np.all(a == 5.0)
    # Non-contiguous and float64 inputs are converted rather than sent wrongly.
    pub.publish_frame(np.arange(32, dtype=np.float64).reshape(4, 8)[:, ::2], 2.0, frame_id=2, deblurred=True)
    _, h, a = sub.recv(2.0)
    assert a.dtype == np.float32 and a.shape == (4, 4) and a[1, 1] == 10.0
    sub.close()


def test_exact_topics_only(pub):
    sub = connect(pub, ("frame",))
    pub.publish_raw(np.zeros((2, 2), np.uint16), 1.0, frame_id=1)
    pub.publish_gyro(np.array([1.0]), np.zeros((1, 3)), seq=0)
    pub.publish_frame(np.zeros((2, 2), np.float32), 1.0, frame_id=1, deblurred=True)
    topic, _, _ = sub.recv(2.0)
    assert topic == "frame" and sub.recv(0.2) is None
    assert "raw" not in sub.received and "gyro" not in sub.received
    sub.close()


def _good(seq=0, **over):
    h = {"v": 1, "seq": seq, "t": 1.0, "published": 1.0, "shape": [2, 3], "dtype": "<u2", "deblurred": False,
         "frame_id": seq}
    h.update(over)
    return h


def test_malformed_messages_are_counted_and_skipped():
    """A hostile/buggy publisher on a raw PUB socket: every bad message is rejected, none crashes."""
    ctx = zmq.Context.instance()
    raw = ctx.socket(zmq.PUB)
    port = raw.bind_to_random_port("tcp://127.0.0.1")
    sub = Subscriber(f"tcp://127.0.0.1:{port}", topics=("raw",), max_header_bytes=2048)
    payload = np.arange(6, dtype="<u2").tobytes()
    ok = [b"raw", json.dumps(_good()).encode(), payload]
    deadline = time.monotonic() + 30      # a hang bound: loaded machines are slow, not stuck
    while sub.recv(0.05) is None:  # warm up
        raw.send_multipart(ok)
        assert time.monotonic() < deadline
    bad = [
        [b"raw", json.dumps(_good()).encode()],                                   # 2 frames
        [b"rawx", json.dumps(_good()).encode(), payload],                         # prefix-matched topic
        [b"raw", b"\xff\xfe not utf8", payload],                                  # not UTF-8
        [b"raw", b"[1, 2, 3]", payload],                                          # not an object
        [b"raw", b'{"v": 1, "seq": NaN}', payload],                               # NaN constant
        [b"raw", json.dumps(_good(v=2)).encode(), payload],                       # future version
        [b"raw", json.dumps(_good(v=True)).encode(), payload],                    # true is not 1
        [b"raw", b"[" * 2000, payload],                                           # nesting bomb
        [b"raw", json.dumps(_good(seq=-1)).encode(), payload],                    # bad seq
        [b"raw", json.dumps(_good(shape=[2, 4])).encode(), payload],              # payload length
        [b"raw", json.dumps(_good(dtype="|O")).encode(), payload],                # object dtype
        [b"raw", json.dumps(_good(shape=[6])).encode(), payload],                 # raw must be 2-D
        [b"raw", json.dumps(_good(t="soon")).encode(), payload],                  # t not a number
        [b"raw", json.dumps(_good(pad="x" * 4000)).encode(), payload],            # header too large
        [b"raw", json.dumps(_good(dtype="packed", shape=[1], layout=[])).encode(), payload],
    ]
    for m in bad:
        raw.send_multipart(m)
    raw.send_multipart([b"raw", json.dumps(_good(seq=7)).encode(), payload])
    got = sub.recv(2.0)
    assert got is not None and got[1]["seq"] == 7 and got[2].tolist() == [[0, 1, 2], [3, 4, 5]]
    assert sum(sub.errors.values()) == len(bad)
    assert sub.errors == {"framing": 1, "topic": 1, "json": 4, "version": 2, "header": 2, "payload_size": 1,
                          "dtype": 1, "shape": 1, "header_size": 1, "layout": 1}
    assert sub.received["raw"] >= 2
    sub.close()
    raw.close(0)


def test_decode_gyro_layout_validation():
    t = np.array([1.0, 2.0])
    r = np.zeros((2, 3), "<f4")
    h = {"v": 1, "seq": 0, "t": 2.0, "published": 2.0, "shape": [2], "dtype": "packed", "deblurred": False,
         "layout": [["t", "<f8", [2]], ["rate", "<f4", [2, 3]]]}
    topic, _, a = decode([b"gyro", json.dumps(h).encode(), t.tobytes() + r.tobytes()])
    assert topic == "gyro" and a["t"].tolist() == [1.0, 2.0]


    with pytest.raises(MessageError, match="covers"):
        decode([b"gyro", json.dumps(h).encode(), t.tobytes() + r.tobytes() + b"\0"])
    h2 = dict(h, layout=[["t", "<f4", [2]], ["rate", "<f4", [2, 3]]])
    with pytest.raises(MessageError, match="dtype"):
        decode([b"gyro", json.dumps(h2).encode(), t.tobytes() + r.tobytes()])
    h3 = dict(h, layout=[["t", "<f8", [2]], ["rate", "<f4", [2, 2]]])
    with pytest.raises(MessageError, match="does not fit"):
        decode([b"gyro", json.dumps(h3).encode(), t.tobytes() + r.tobytes()])


def test_seq_gaps_and_restarts_are_counted():
    ctx = zmq.Context.instance()
    raw = ctx.socket(zmq.PUB)
    port = raw.bind_to_random_port("tcp://127.0.0.1")
    sub = Subscriber(f"tcp://127.0.0.1:{port}", topics=("raw",))
    payload = np.zeros(6, "<u2").tobytes()
    deadline = time.monotonic() + 30      # a hang bound: loaded machines are slow, not stuck
    while sub.recv(0.05) is None:
        raw.send_multipart([b"raw", json.dumps(_good(seq=0)).encode(), payload])
        assert time.monotonic() < deadline
    while sub.recv(0.05) is not None:
        pass
    sub.gaps.clear()
    sub.restarts.clear()
    for s in (1, 2, 5, 6, 10, 0, 1):  # lost 3,4 and 7,8,9; then the publisher restarted at 0
        raw.send_multipart([b"raw", json.dumps(_good(seq=s)).encode(), payload])
    seqs = [sub.recv(2.0)[1]["seq"] for _ in range(7)]
    assert seqs == [1, 2, 5, 6, 10, 0, 1]
    assert sub.gaps["raw"] == 5 and sub.restarts["raw"] == 1
    sub.close()
    raw.close(0)


def test_queue_drops_oldest_without_blocking():
    p = Publisher(EP, queue_size=4)  # not started: nothing drains the queue
    seqs = [p.publish_frame(np.zeros((2, 2), np.float32), i, frame_id=i, deblurred=True) for i in range(10)]
    st = p.stats()
    assert seqs == list(range(10))
    assert st["queue_dropped"] == 6 and st["queue_depth"] == 4 and st["queued"]["frame"] == 10
    assert [m[1]["seq"] for m in p._queue] == [6, 7, 8, 9]  # the newest survive; the gap shows up as seq
    # The byte bound: three 1 MiB frames fit a 2.5 MiB queue only two at a time; gyro batches still do.
    p = Publisher(EP, queue_size=100, queue_bytes=5 << 19, gyro_batch_s=0)
    big = np.zeros((512, 512), np.float32)
    for i in range(3):
        p.publish_frame(big, i, frame_id=i, deblurred=True)
    p.publish_gyro(np.arange(10.0), np.zeros((10, 3)), seq=0)
    st = p.stats()
    assert st["queue_dropped"] == 1 and st["queue_depth"] == 3
    assert st["queue_bytes"] == 2 * big.nbytes + 10 * (8 + 12)
    assert [m[1]["seq"] for m in p._queue] == [1, 2, 0]


@pytest.mark.slow
def test_slow_subscriber_never_blocks_the_publisher():
    p = Publisher(EP, hwm=4, queue_size=8).start()
    try:
        lazy = connect(p, ("frame",), rcvhwm=4)  # connected, then never reads while we publish
        img = np.ones((256, 512), np.float32)  # 512 KiB per message
        n = 300
        for i in range(n):
            p.publish_frame(img, float(i), frame_id=i, deblurred=True)
            time.sleep(0.0005)
        # every message sent or counted as dropped, once the sender has handled the last one (the queue
        # empties when it takes the last message, before that message is sent and counted)
        def accounted(st):
            return st["sent"]["frame"] + st["queue_dropped"] + st["budget_dropped"]["frame"]

        deadline = time.monotonic() + 20
        while accounted(p.stats()) < n and time.monotonic() < deadline:
            time.sleep(0.01)
        st = p.stats()
        assert accounted(st) == n and st["send_errors"] == 0
        got = []
        while (m := lazy.recv(0.5)) is not None:
            got.append(m[1]["seq"])
        assert 0 < len(got) < n  # HWM dropped most of them (150 MiB would not fit the buffers)
        assert lazy.gaps["frame"] == got[-1] - got[0] + 1 - len(got)
        assert (lazy.first_seq["frame"], lazy.last_seq["frame"]) == (got[0], got[-1])
        assert got == sorted(got)
        lazy.close()
    finally:
        p.stop()


def test_bind_errors_and_bad_input_are_clear(tmp_path):
    with Publisher(EP) as a:
        with pytest.raises(TransportError, match=a.endpoint.replace(".", r"\.")):
            Publisher(a.endpoint).start()
    with pytest.raises(TransportError, match="missing.key_secret"):
        Publisher(EP, curve_secret_key_file=tmp_path / "missing.key_secret")
    public, secret = zmq.auth.create_certificates(tmp_path, "srv")
    Path(secret).chmod(0o600)
    with pytest.raises(TransportError, match="no secret key"):
        Publisher(EP, curve_secret_key_file=public)
    with pytest.raises(TransportError, match=r"curve_secret_key: missing \(curve_authorized_keys needs"):
        Publisher(EP, authorized_keys_dir=tmp_path)
    with pytest.raises(TransportError, match="not a directory"):
        Publisher(EP, curve_secret_key_file=tmp_path / "srv.key_secret", authorized_keys_dir=tmp_path / "no")
    assert issubclass(TransportError, ThermodError)
    p = Publisher(EP)
    with pytest.raises(ValueError, match="unknown topic"):
        p.publish("frames", {"t": 0.0}, np.zeros(1, np.float32))
    with pytest.raises(ValueError, match="uint16"):
        p.publish_raw(np.zeros((2, 2), np.float32), 0.0, frame_id=0)
    with pytest.raises(ValueError, match="not allowed"):
        p.publish("frame", {"t": 0.0}, np.zeros((2, 2), np.complex64))
    with pytest.raises(ValueError, match=r"\[3, 3\] to match"):
        p.publish_gyro(np.zeros(3), np.zeros((3, 2)), seq=0)


def _certs(tmp_path):
    keys, auth_dir = tmp_path / "keys", tmp_path / "authorized"
    auth_dir.mkdir()
    keys.mkdir()
    zmq.auth.create_certificates(keys, "server")
    ok_public, _ = zmq.auth.create_certificates(keys, "good")
    zmq.auth.create_certificates(keys, "evil")
    for secret in keys.glob("*.key_secret"):
        secret.chmod(0o600)  # create_certificates leaves them at the umask; the publisher refuses that
    (auth_dir / "good.key").write_bytes(open(ok_public, "rb").read())
    return keys, auth_dir


@pytest.mark.slow
def test_curve_only_authorised_clients_receive(tmp_path):
    keys, auth_dir = _certs(tmp_path)
    p = Publisher(EP, curve_secret_key_file=keys / "server.key_secret", authorized_keys_dir=auth_dir).start()
    try:
        good = Subscriber(p.endpoint, ("frame",), curve_server_key=keys / "server.key",
                          curve_client_key_file=keys / "good.key_secret")
        evil = Subscriber(p.endpoint, ("frame",), curve_server_key=keys / "server.key",
                          curve_client_key_file=keys / "evil.key_secret")
        plain = Subscriber(p.endpoint, ("frame",))
        wrong_server = Subscriber(p.endpoint, ("frame",), curve_server_key=keys / "evil.key",
                                  curve_client_key_file=keys / "good.key_secret")
        img = np.full((4, 4), 3.0, np.float32)
        received = {"good": 0, "evil": 0, "plain": 0, "wrong_server": 0}
        subs = {"good": good, "evil": evil, "plain": plain, "wrong_server": wrong_server}
        deadline = time.monotonic() + 60      # until the good one got 11 (CURVE handshakes are slow
        i = 0                                 # on a loaded machine); 60 s only catches a hang
        while received["good"] <= 10:
            assert time.monotonic() < deadline, received
            p.publish_frame(img, float(i), frame_id=i, deblurred=True)
            i += 1
            for name, s in subs.items():
                while (m := s.recv(0.0)) is not None:
                    received[name] += 1
                    assert np.all(m[2] == 3.0)
            time.sleep(0.02)
        assert received["good"] > 10
        assert received["evil"] == received["plain"] == received["wrong_server"] == 0
        for s in subs.values():
            s.close()
    finally:
        p.stop()


def test_curve_encryption_without_client_allowlist(tmp_path):
    keys, _ = _certs(tmp_path)
    with Publisher(EP, curve_secret_key_file=keys / "server.key_secret") as p:
        pub_key = open(keys / "server.key", "rb").read()
        server_public = zmq.auth.load_certificate(keys / "server.key")[0]
        assert p.public_key == server_public and b"public-key" in pub_key
        sub = connect(p, ("frame",), curve_server_key=server_public)  # throwaway client key pair
        p.publish_frame(np.ones((2, 2), np.float32), 1.0, frame_id=1, deblurred=True)
        topic, h, a = sub.recv(2.0)
        assert topic == "frame" and h["frame_id"] == 1
        sub.close()


def test_inproc_with_a_shared_context():
    ctx = zmq.Context()
    try:
        with Publisher("inproc://thermod-test", context=ctx) as p:
            sub = connect(p, ("frame",), context=ctx)
            p.publish_frame(np.eye(3, dtype=np.float32), 5.0, frame_id=9, deblurred=True)
            topic, h, a = sub.recv(2.0)
            assert topic == "frame" and h["frame_id"] == 9 and np.array_equal(a, np.eye(3))
            sub.close()
        assert not ctx.closed  # a shared context stays the caller's
    finally:
        ctx.term()


def test_gyro_batches_are_coalesced_but_never_across_a_gap():
    p = Publisher(EP, gyro_batch_s=5.0).start()  # long: only contiguity and stop() decide here
    try:
        sub = connect(p, ("gyro",))
        t = 50.0 + np.arange(40) * 1e-3
        rate = np.arange(120, dtype=np.float32).reshape(40, 3)
        for s in range(0, 20, 2):  # 10 driver batches of 2 contiguous samples
            assert p.publish_gyro(t[s:s + 2], rate[s:s + 2], seq=1000 + s) is None
        # 5 samples lost in the driver: the pending 20 go out as one message, the rest start a new one
        assert p.publish_gyro(t[25:27], rate[25:27], seq=1025, gap_before=True, n_lost=5) == 0
        assert p.publish_gyro(t[27:40], rate[27:40], seq=1027) is None
        _, h0, a0 = sub.recv(2.0)
        assert (h0["seq"], h0["n"], h0["sample_seq"], h0["gap_before"]) == (0, 20, 1000, False)
        assert np.array_equal(a0["t"], t[:20]) and np.array_equal(a0["rate"], rate[:20]) and h0["t"] == t[19]
        assert sub.recv(0.3) is None  # the second one is still being coalesced
    finally:
        p.stop()  # flushes what is pending
    _, h1, a1 = sub.recv(2.0)
    assert (h1["seq"], h1["n"], h1["sample_seq"], h1["gap_before"], h1["n_lost"]) == (1, 15, 1025, True, 5)
    assert np.array_equal(a1["t"], t[25:]) and np.array_equal(a1["rate"], rate[25:])
    sub.close()


def test_gyro_coalescing_flushes_on_time():
    with Publisher(EP, gyro_batch_s=0.05) as p:
        sub = connect(p, ("gyro",))
        p.publish_gyro(np.array([1.0, 1.001]), np.zeros((2, 3)), seq=0)  # and then the gyro goes quiet
        m = sub.recv(2.0)
        assert m is not None and m[1]["n"] == 2
        assert m[1]["published"] - m[1]["t"] > 0  # sent by the timer, not by a following batch
        sub.close()
    with Publisher(EP, gyro_batch_s=0) as p:  # no coalescing: one message per call
        assert [p.publish_gyro(np.array([float(i)]), np.zeros((1, 3)), seq=i) for i in range(3)] == [0, 1, 2]


def test_a_gyro_batch_being_coalesced_wakes_the_sender_once():
    """Each wake is a pass of the sender's loop in the daemon's Python: a driver batch every 1–2 ms
    woke it for every call, though only the batch's start (to arm its timer) and a message need it."""
    p = Publisher(EP, gyro_batch_s=5.0)
    wakes = []
    real_set = p._wake.set
    p._wake.set = lambda: wakes.append(1) or real_set()
    for s in range(0, 40, 2):
        assert p.publish_gyro(1.0 + np.arange(s, s + 2) * 1e-3, np.zeros((2, 3)), seq=s) is None
    assert len(wakes) == 1
    p.publish_gyro(np.array([2.0]), np.zeros((1, 3)), seq=100)   # not contiguous: one message, one batch
    assert len(wakes) == 3


def test_the_daemon_s_gyro_messages_follow_its_configuration():
    from thermod.runtime import config
    from thermod.runtime.daemon import Daemon

    assert config.load(None).publish.gyro_batch_s == 0.05
    d = Daemon(config.load(None, {"publish.gyro_batch_s": 0.2, "publish.endpoint": EP}))  # not started
    assert d.publisher.gyro_batch_s == 0.2
    with pytest.raises(ConfigError, match="publish.gyro_batch_s"):
        config.load(None, {"publish.gyro_batch_s": 2.0})


# ------------------------------------------------------------------------------ endpoints and security
def test_a_second_publisher_cannot_steal_a_live_ipc_endpoint(tmp_path):
    ep = f"ipc://{tmp_path / 'pub.sock'}"
    with Publisher(ep) as first:
        sub = connect(first, ("frame",))
        with pytest.raises(TransportError, match="already publishing"):
            Publisher(ep).start()
        # the first one still owns the socket: its subscriber keeps receiving
        first.publish_frame(np.full((2, 2), 7.0, np.float32), 1.0, frame_id=1, deblurred=True)
        m = sub.recv(2.0)
        assert m is not None and m[1]["frame_id"] == 1
        sub.close()


def test_a_stale_ipc_socket_file_is_removed_and_a_regular_file_is_not(tmp_path):
    import socket
    path = tmp_path / "stale.sock"
    dead = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    dead.bind(str(path))
    dead.close()            # the file stays, nobody listens: what a killed daemon leaves behind
    assert path.is_socket()
    with Publisher(f"ipc://{path}") as p:
        sub = connect(p, ("frame",))
        p.publish_frame(np.zeros((2, 2), np.float32), 1.0, frame_id=3, deblurred=True)
        assert sub.recv(2.0)[1]["frame_id"] == 3
        sub.close()
    keep = tmp_path / "data.bin"
    keep.write_bytes(b"precious")
    with pytest.raises(TransportError, match="not a socket"):
        Publisher(f"ipc://{keep}").start()
    assert keep.read_bytes() == b"precious"


@pytest.mark.parametrize("endpoint, why", [
    ("tcp://127.0.0.1:99999", "1–65535"),
    ("tcp://127.0.0.1:0", "1–65535"),
    ("tcp://127.0.0.1:55x", "1–65535"),
    ("tcp://127.0.0.1", "HOST:PORT"),
    ("tcp://:5555", "HOST:PORT"),
    ("tcp://[::zz]:5555", "IPv6"),
    ("udp://127.0.0.1:5555", "tcp://HOST:PORT"),
    ("127.0.0.1:5555", "tcp://HOST:PORT"),
    ("ipc://", "empty"),
    ("tcp://127.0.0.1:5555 ", "blanks"),
])
def test_malformed_endpoints_are_refused_naming_publish_endpoint(endpoint, why):
    with pytest.raises(TransportError, match="publish.endpoint") as e:
        Publisher(endpoint)
    assert why in str(e.value) and repr(endpoint) in str(e.value)
    with pytest.raises(ThermodError, match=r"publish\.endpoint"):
        config.load(None, {"publish.endpoint": endpoint})


def test_loopback_classification():
    for ep in ("tcp://127.0.0.1:1", "tcp://127.3.0.1:1", "tcp://localhost:1", "tcp://[::1]:1", "tcp://lo:1",
               "ipc:///run/thermod/pub.sock", "inproc://x"):
        assert is_loopback(ep), ep
    for ep in ("tcp://0.0.0.0:1", "tcp://*:1", "tcp://[::]:1", "tcp://10.1.2.3:1", "tcp://eth0:1",
               "tcp://camera.local:1"):
        assert not is_loopback(ep), ep


def test_a_remote_bind_needs_curve_or_an_explicit_insecure_opt_in(tmp_path, caplog):
    with pytest.raises(TransportError, match="allow_insecure_remote"):
        Publisher("tcp://0.0.0.0:*")
    with pytest.raises(ThermodError, match=r"publish\.endpoint.*allow_insecure_remote"):
        config.load(None, {"publish.endpoint": "tcp://0.0.0.0:5555"})
    cfg = config.load(None, {"publish.endpoint": "tcp://0.0.0.0:5555", "publish.allow_insecure_remote": True})
    assert cfg.publish.allow_insecure_remote
    with caplog.at_level("WARNING", logger="thermod.runtime.publish"):
        with Publisher("tcp://0.0.0.0:*", allow_insecure_remote=True) as p:
            assert any("insecure_remote" in w for w in p.stats()["warnings"])
    assert "without CURVE" in caplog.text
    keys, _ = _certs(tmp_path)
    with Publisher("tcp://0.0.0.0:*", curve_secret_key_file=keys / "server.key_secret") as p:
        assert p.running and p.stats()["warnings"] == []


@pytest.mark.parametrize("mode", [0o644, 0o640, 0o604, 0o660])
def test_a_curve_secret_key_readable_by_others_is_refused(tmp_path, mode):
    keys, _ = _certs(tmp_path)
    secret = keys / "server.key_secret"
    secret.chmod(mode)
    with pytest.raises(TransportError, match=f"readable by group or others.*{mode:04o}"):
        Publisher(EP, curve_secret_key_file=secret)
    client = keys / "good.key_secret"
    client.chmod(mode)
    with pytest.raises(TransportError, match="readable by group or others"):
        Subscriber("tcp://127.0.0.1:5999", curve_server_key=keys / "server.key", curve_client_key_file=client)
    secret.chmod(0o600)
    with Publisher(EP, curve_secret_key_file=secret) as p:
        assert p.running


# ------------------------------------------------------------------------------------ memory bounds
def test_the_byte_budget_sizes_the_hwm():
    p = Publisher(EP, hwm=100, max_queue_bytes=64 << 20, max_message_bytes=640 * 480 * 4)
    assert p.hwm == (64 << 20) // (2 * 640 * 480 * 4) - 1 == 26  # 640×480 float32 frames
    assert Publisher(EP, hwm=5, max_queue_bytes=64 << 20, max_message_bytes=1000).hwm == 5
    assert Publisher(EP, hwm=100, max_queue_bytes=1 << 20, max_message_bytes=1 << 20).hwm == 2
    assert config.load(None, {}).publish.max_queue_mb == 128.0


def _stalled(ctx, endpoint):
    """A subscriber that connects and never reads."""
    s = ctx.socket(zmq.SUB)
    s.setsockopt(zmq.RCVHWM, 1)
    s.setsockopt(zmq.LINGER, 0)
    s.setsockopt(zmq.SUBSCRIBE, b"frame")
    s.connect(endpoint)
    return s


@pytest.mark.slow
def test_stalled_subscribers_cannot_grow_the_publisher_beyond_its_budget():
    """inproc: no kernel socket buffers, so what each stalled subscriber holds is ZeroMQ's queue alone
    (over tcp the kernel absorbs a few MB more per connection, outside the process)."""
    mib = 1 << 20
    budget = 24 * mib
    img = np.zeros((512, 512), np.float32)                    # 1 MiB
    ctx = zmq.Context()
    p = Publisher("inproc://budget", hwm=100, max_queue_bytes=budget, max_message_bytes=img.nbytes,
                  context=ctx).start()
    assert p.hwm == budget // ((BUDGETED_STALLED_SUBSCRIBERS + 1) * mib) - 1
    stalled, healthy = [], None
    try:
        healthy = connect(p, ("frame",), context=ctx)
        frame_id = 0

        def publish_and_read(n, wait=2.0):
            """Frames one at a time, each read by the healthy subscriber before the next."""
            got = 0
            for _ in range(n):
                nonlocal frame_id
                frame_id += 1
                p.publish_frame(img, float(frame_id), frame_id=frame_id, deblurred=True)
                m = healthy.recv(wait)
                got += m is not None and m[1]["frame_id"] == frame_id
            return got

        # the budgeted stalled subscriber: the healthy one loses nothing
        for _ in range(BUDGETED_STALLED_SUBSCRIBERS):
            stalled.append(_stalled(ctx, p.endpoint))
            assert publish_and_read(20) == 20
        assert p.stats()["held_bytes"] >= BUDGETED_STALLED_SUBSCRIBERS * (p.hwm + 1) * mib  # really held
        assert p.stats()["budget_dropped_total"] == 0
        # many more: the publisher drops and counts rather than grows
        for _ in range(8):
            stalled.append(_stalled(ctx, p.endpoint))
            publish_and_read(20, wait=0.01)
        s = p.stats()
        assert s["budget_dropped"]["frame"] > 0
        assert s["held_peak_bytes"] <= budget and s["held_bytes"] <= budget
        assert s["held_bytes"] > budget - 2 * mib
        # once the stalled subscribers leave, their queues are released and frames flow again
        for st in stalled:
            st.close()
        stalled.clear()
        deadline = time.monotonic() + 30      # a hang bound: loaded machines are slow, not stuck
        while time.monotonic() < deadline and p.stats()["held_bytes"] > 0:
            time.sleep(0.05)
        assert p.stats()["held_bytes"] == 0
        assert publish_and_read(10) == 10
    finally:
        for st in stalled:
            st.close()
        if healthy is not None:
            healthy.close()
        p.stop()
        ctx.term()


@pytest.mark.slow
def test_a_frozen_subscriber_is_dropped_by_heartbeats_and_its_queue_freed():
    """A hung client (SIGSTOP: not even its ZeroMQ I/O thread runs) answers no heartbeat."""
    import subprocess
    import sys
    img = np.zeros((512, 512), np.float32)                    # 1 MiB
    with Publisher(EP, stall_timeout_s=1.0, max_message_bytes=img.nbytes) as p:
        frozen = subprocess.Popen([sys.executable, "-c", FROZEN_SUBSCRIBER, p.endpoint])
        try:
            deadline = time.monotonic() + 30
            peak, i = 0, 0
            # its queue fills (a transient in-flight frame or two is not that), then is freed; with a
            # 60 s timeout instead, 19 MiB stay held
            while peak < 8 * img.nbytes or p.stats()["held_bytes"] > 0:
                assert time.monotonic() < deadline, f"held {p.stats()['held_bytes']} B, peak {peak} B"
                i += 1
                p.publish_frame(img, float(i), frame_id=i, deblurred=True)
                peak = max(peak, p.stats()["held_bytes"])
                time.sleep(0.02)
        finally:
            frozen.kill()
            frozen.wait()


def _rogue_message(n_bytes):
    h = {"v": 1, "seq": 0, "t": 1.0, "published": 1.0, "shape": [1, n_bytes // 4], "dtype": "<f4",
         "deblurred": True}
    return [b"frame", json.dumps(h).encode(), bytes(n_bytes)]


@pytest.mark.parametrize("limit_mib, delivered", [(1, False), (16, True)])
def test_maxmsgsize_drops_an_oversized_message_on_its_size_prefix(limit_mib, delivered):
    ctx = zmq.Context()
    rogue = ctx.socket(zmq.PUB)
    rogue.setsockopt(zmq.LINGER, 0)
    port = rogue.bind_to_random_port("tcp://127.0.0.1")
    monitor = rogue.get_monitor_socket(zmq.EVENT_DISCONNECTED)
    sub = Subscriber(f"tcp://127.0.0.1:{port}", ("frame",), max_message_bytes=limit_mib << 20)
    try:
        deadline = time.monotonic() + 30      # a hang bound: loaded machines are slow, not stuck
        while sub.recv(0.05) is None:       # slow joiner: small valid messages until one arrives
            assert time.monotonic() < deadline, "subscriber never connected"
            rogue.send_multipart(_rogue_message(64))
        rogue.send_multipart(_rogue_message(8 << 20))         # 8 MiB
        m = sub.recv(2.0)
        if delivered:
            assert m is not None and m[2].nbytes == 8 << 20
        else:
            assert m is None
            # the subscriber hung up on reading the size prefix (the rogue sees the disconnect)
            assert monitor.poll(2000)
            from zmq.utils.monitor import recv_monitor_message
            assert recv_monitor_message(monitor)["event"] == zmq.EVENT_DISCONNECTED
            # and it dials again: small messages flow again
            assert sub.disconnects == 1
            deadline = time.monotonic() + 30      # a hang bound: loaded machines are slow, not stuck
            while sub.recv(0.05) is None:
                assert time.monotonic() < deadline, "subscriber did not reconnect"
                rogue.send_multipart(_rogue_message(64))
    finally:
        sub.close()
        rogue.disable_monitor()
        monitor.close(0)
        rogue.close(0)
        ctx.term()


def test_a_subscriber_follows_a_restarted_publisher_on_one_connection():
    first = Publisher(EP).start()
    endpoint = first.endpoint
    sub = connect(first, ("frame",))
    first.stop()
    with Publisher(endpoint) as second:
        deadline = time.monotonic() + 30      # a hang bound: loaded machines are slow, not stuck
        while True:   # warm up again: the subscription must reach the new publisher
            assert time.monotonic() < deadline, "subscriber did not follow the restart"
            second.publish_health()
            if sub.recv(0.1) is not None:
                break
        while sub.recv(0.2) is not None:
            pass
        second.publish_frame(np.zeros((2, 2), np.float32), 1.0, frame_id=5, deblurred=True)
        assert sub.recv(2.0)[1]["frame_id"] == 5
        assert sub.recv(0.3) is None            # once: no second connection delivers a duplicate
    assert sub.disconnects >= 1
    sub.close()


@pytest.mark.parametrize("kind", ["tcp", "ipc"])
def test_a_second_daemon_fails_on_a_taken_endpoint_before_preparing_its_payload(tmp_path, kind):
    from thermod.runtime.daemon import Daemon
    ep = EP if kind == "tcp" else f"ipc://{tmp_path / 'pub.sock'}"
    cache = tmp_path / "cache"
    cache.mkdir()
    with Publisher(ep) as first:
        cfg = config.load(None, {"publish.endpoint": first.endpoint, "sim.cache_dir": str(cache)})
        d = Daemon(cfg)
        try:
            with pytest.raises(TransportError, match="second thermod"):
                d.start()
            assert d.payload.loop is None and list(cache.iterdir()) == []   # nothing was rendered
        finally:
            d.stop()
        assert first.running


def test_an_insecure_remote_bind_is_reported_in_the_daemon_health(tmp_path):
    from thermod.runtime.daemon import Daemon
    cfg = config.load(None, {"publish.endpoint": "tcp://0.0.0.0:*", "publish.allow_insecure_remote": True,
                             "sim.cache_dir": str(tmp_path)})
    d = Daemon(cfg)
    try:
        h = d.health()
        assert any("insecure_remote" in w for w in h["publisher"]["warnings"])
        assert h["drops"]["publish_budget_dropped"] == 0 and h["publisher"]["hwm"] >= 2
    finally:
        d.stop()


def test_one_loopback_rule_and_one_set_of_transport_defaults():
    """The publisher, the RTSP server and the web view ask one rule whether a bind is private, and the
    configuration's defaults are the publisher's."""
    from thermod.io.endpoints import DEFAULT_HWM, is_loopback, is_loopback_host

    for host in ("127.0.0.1", "127.8.0.1", "::1", "[::1]", "localhost", "lo"):
        assert is_loopback_host(host), host
    for host in ("0.0.0.0", "::", "*", "192.168.1.2", "eth0", "example.org", ""):
        assert not is_loopback_host(host), host
    assert is_loopback("tcp://[::1]:5555") and is_loopback("ipc:///tmp/x") and is_loopback("inproc://a")
    assert not is_loopback("tcp://0.0.0.0:5555") and not is_loopback("tcp://*:5555")
    cfg = config.load()
    assert Publisher().hwm == cfg.publish.hwm == DEFAULT_HWM
    assert Publisher().max_queue_bytes == int(cfg.publish.max_queue_mb * 2**20)
    assert Publisher().endpoint == cfg.publish.endpoint


def test_an_ipc_publisher_removes_its_socket_file_and_listening_tells(tmp_path):
    from thermod.io.endpoints import listening

    ep = f"ipc://{tmp_path / 'p.sock'}"
    assert listening(ep) is False                   # no file yet
    with Publisher(ep):
        assert (tmp_path / "p.sock").is_socket() and listening(ep) is True
    assert not (tmp_path / "p.sock").exists() and listening(ep) is False
    with Publisher("tcp://127.0.0.1:*") as p:
        port_ep = p.endpoint
        assert listening(port_ep) is True
    assert listening(port_ep) is False
    assert listening("inproc://x") is None


def _until(cond, timeout=30.0):
    """Poll `cond` until true or `timeout` (a hang bound on a loaded machine, not a rate)."""
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, "condition never held"
        time.sleep(0.01)


def test_wants_follows_what_plain_zmq_subscribers_subscribe_to(pub):
    """XPUB hears each subscription: `wants` holds for a subscribed topic (or a prefix of it, ""
    included) while a subscriber asks for it, and not after its last subscriber unsubscribes or
    closes. The subscribers are bare pyzmq SUB sockets."""
    ctx = zmq.Context.instance()
    assert not pub.wants("kernel") and not pub.wants("frame")
    a = ctx.socket(zmq.SUB)
    a.connect(pub.endpoint)
    a.setsockopt(zmq.SUBSCRIBE, b"kernel")
    _until(lambda: pub.wants("kernel"))
    assert not pub.wants("frame") and not pub.wants("raw")
    b = ctx.socket(zmq.SUB)
    b.connect(pub.endpoint)
    b.setsockopt(zmq.SUBSCRIBE, b"kernel")
    b.setsockopt(zmq.SUBSCRIBE, b"fr")                       # a prefix of "frame"
    _until(lambda: pub.wants("frame"))
    a.setsockopt(zmq.UNSUBSCRIBE, b"kernel")
    time.sleep(0.5)                                          # b still asks for it
    assert pub.wants("kernel")
    b.close(linger=0)                                        # its connection closes: nobody asks
    _until(lambda: not pub.wants("kernel") and not pub.wants("frame"))
    a.setsockopt(zmq.SUBSCRIBE, b"")                         # everything
    _until(lambda: pub.wants("kernel") and pub.wants("health"))
    # and messages still flow to it as from a PUB socket
    pub.publish_health()
    assert a.poll(5000) and a.recv_multipart()[0] == b"health"
    a.close(linger=0)

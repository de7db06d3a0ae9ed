"""A chaos soak: the daemon, in-process on the simulated payload, under a seeded random schedule of
faults, with every camera frame accounted for. `run` returns a result dict, `table` prints it; both
`benchmarks/bench_chaos.py` (minutes) and `tests/runtime/test_chaos.py` (60 s) use them.

Faults, one every 1–3 s (`schedule`):

- gyro unplug/replug and NACK (the register emulator: ``payload.chip.unplug(s)`` / ``nack(n)``), FIFO
  overflow (the gyro polling thread starved: `HiccupGyro.pause`), clock jumps (`HiccupGyro.jump_back`);
- camera stall and disconnect (``SimCamera.stall(s)`` / ``disconnect(s)``);
- SIGHUP-style reloads (the reload event of `Daemon.serve`) of a rewritten config file: good ones (a
  changed ``tau_s`` and ``lambda``) must be applied, bad ones (`BAD_CONFIGS`: an out-of-range value, a
  non-UTF-8 byte, truncated TOML, a calibration for another frame size) refused with the running
  settings kept;
- 0–4 stalled subscribers (raw SUB sockets that connect and never read) and subscribers that connect,
  read a while and leave.

Accounting: a subscriber reading every frame (large RCVHWM, seq gaps counted) is compared with what the
camera source delivered and the daemon's named drop counters. At the end the camera is silenced and the
pipeline drained, so every delivered frame is either published, or counted under a reason; the rest is
``unaccounted``. The systemd side is played by `NotifyListener` (WATCHDOG=1 receipt times).
"""

from __future__ import annotations

import collections
import contextlib
import os
import random
import re
import socket
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import zmq

from thermod.client.subscriber import Subscriber
from thermod.runtime import config as configmod
from thermod.runtime.daemon import Daemon
from thermod.runtime.sdnotify import Notifier
from thermod.sim.payload import SimPayload

GYRO_FAULTS = ("gyro_unplug", "gyro_nack", "fifo_overflow", "clock_jump")
CAMERA_FAULTS = ("camera_stall", "camera_disconnect")
RELOADS = ("reload_good", "reload_bad")
SUBSCRIBER_FAULTS = ("stalled_subscribers", "subscriber_churn")
KINDS = GYRO_FAULTS + CAMERA_FAULTS + RELOADS + SUBSCRIBER_FAULTS
BAD_CONFIGS = ("out_of_range", "non_utf8", "truncated", "wrong_size")
# values the config loader must refuse (each names its key in the error)
_OUT_OF_RANGE = (("tau_s", "-1.0"), ("pixel_pitch_um", "0.0"), ("psf_beta", "0.0"), ("frame_rate_hz", "0.0"))


# ------------------------------------------------------------------------------------ fault sources
class HiccupGyro:
    """The real ICM-42688-P driver, whose polling thread can be starved for a while (as by a
    priority inversion): the chip's FIFO then overflows exactly as on hardware."""

    def __init__(self, inner):
        self.inner, self.name, self._pause, self._shift = inner, inner.name, 0.0, 0.0

    def pause(self, seconds):
        self._pause = seconds

    def start(self):
        self.inner.start()

    def stop(self):
        self.inner.stop()

    def stats(self):
        return self.inner.stats()

    @property
    def clock(self):
        return self.inner.clock

    def jump_back(self, seconds):
        """The next batch is stamped `seconds` early (a glitch of the device → host clock mapping)."""
        self._shift = seconds

    def poll(self, timeout):
        if self._pause:
            p, self._pause = self._pause, 0.0
            time.sleep(p)
        b = self.inner.poll(timeout)
        if b is not None and self._shift:
            b.t = b.t - self._shift
            self._shift = 0.0
        return b


@dataclass(frozen=True)
class Fault:
    at: float                 # seconds after the soak started
    kind: str                 # one of KINDS
    arg: object = None        # duration, count, or the config variant


def schedule(seconds: float, seed: int = 0, *, gap_s=(1.0, 3.0), quiet_s: float = 4.0) -> list[Fault]:
    """A fault every U(gap_s) seconds until ``seconds − quiet_s`` (the end is left quiet so every
    fault has ended before the daemon is checked). Kinds are dealt from shuffled rounds of `KINDS`
    (bad reloads twice per round, their variants from shuffled rounds of `BAD_CONFIGS`), so a short
    soak still meets every kind."""
    rng = random.Random(seed)

    def dealer(items):
        while True:
            yield from rng.sample(items, len(items))
    kinds, variants = dealer((*KINDS, "reload_bad")), dealer(BAD_CONFIGS)
    out, t = [], rng.uniform(*gap_s)
    while t < seconds - quiet_s:
        kind = next(kinds)
        arg = {"gyro_unplug": lambda: round(rng.uniform(0.2, 1.0), 2),
               "gyro_nack": lambda: rng.randint(1, 5),
               "fifo_overflow": lambda: round(rng.uniform(0.3, 0.8), 2),   # > 256 samples at 1 kHz
               "clock_jump": lambda: round(rng.uniform(0.05, 0.6), 3),
               "camera_stall": lambda: round(rng.uniform(0.5, 2.0), 2),
               "camera_disconnect": lambda: round(rng.uniform(0.2, 1.5), 2),
               "reload_good": lambda: (round(rng.uniform(0.0075, 0.0090), 5),       # tau_s, lambda
                                       round(rng.uniform(500, 5000), 1)),
               "reload_bad": lambda: (next(variants), rng.randrange(1 << 30)),
               "stalled_subscribers": lambda: rng.randint(0, 4),
               "subscriber_churn": lambda: round(rng.uniform(0.3, 3.0), 2)}[kind]()
        out.append(Fault(round(t, 3), kind, arg))
        t += rng.uniform(*gap_s)
    return out


def good_config(base: str, tau_s: float, lam: float) -> bytes:
    """The config text with calibration.tau_s and deblur.lambda changed."""
    text = re.sub(r"(?m)^tau_s\s*=.*$", f"tau_s = {tau_s!r}", base)
    text = re.sub(r"(?m)^lambda\s*=.*\n", "", text)
    return text.replace("[deblur]\n", f"[deblur]\nlambda = {lam!r}\n", 1).encode()


def bad_config(base: str, variant: str, seed: int) -> bytes:
    """A config file the daemon must refuse: `variant` is one of `BAD_CONFIGS`."""
    rng = random.Random(seed)
    if variant == "out_of_range":
        key, value = rng.choice(_OUT_OF_RANGE)
        return re.sub(rf"(?m)^{key}\s*=.*$", f"{key} = {value}", base, count=1).encode()
    if variant == "non_utf8":
        lines = base.encode().split(b"\n")
        i = rng.randrange(len(lines))
        lines[i] += rng.choice([b" # \xe9t\xe9", b" # \xff", b" # \xc3"])
        return b"\n".join(lines)
    if variant == "truncated":
        # cut inside an array or a string value, so what is left can never be valid TOML
        cut = rng.choice([m.end() for m in re.finditer(r'= *[\["]', base)])
        return base[:cut + (rng.randrange(3) if base[cut - 1] == "[" else 0)].encode()
    if variant == "wrong_size":
        w, h = rng.choice([(320, 240), (640, 512), (320, 480), (1280, 960)])
        text = re.sub(r"(?m)^width\s*=.*$", f"width = {w}", base, count=1)
        return re.sub(r"(?m)^height\s*=.*$", f"height = {h}", text, count=1).encode()
    raise ValueError(f"unknown bad config variant {variant!r}; expected one of {BAD_CONFIGS}")


# ------------------------------------------------------------------------------------ observers
class NotifyListener(threading.Thread):
    """systemd's side of $NOTIFY_SOCKET: a datagram socket read continuously; every message is kept
    with its receipt time (host monotonic)."""

    def __init__(self, path: str):
        super().__init__(name="chaos-notify", daemon=True)
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(path)
        self.sock.settimeout(0.1)
        self.msgs: list[tuple[float, str]] = []
        self._halt = threading.Event()

    def run(self):
        while not self._halt.is_set():
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            self.msgs.append((time.monotonic(), data.decode(errors="replace")))

    def pings(self, since: float = -float("inf")) -> list[float]:
        return [t for t, m in list(self.msgs) if t >= since and "WATCHDOG=1" in m.split("\n")]

    def longest_gap(self, since: float, until: float) -> float:
        """Longest time without a WATCHDOG=1 in [since, until] (the ends count as edges)."""
        edges = [since, *self.pings(since), until]
        edges = [t for t in edges if t <= until]
        return max(b - a for a, b in zip(edges, edges[1:], strict=False)) if len(edges) > 1 else 0.0

    def close(self):
        self._halt.set()
        self.join(2)
        self.sock.close()
        with contextlib.suppress(OSError):
            os.unlink(self.path)


class AccountingSubscriber(threading.Thread):
    """Reads every frame as fast as it comes (a large RCVHWM: the wire must never drop for it) and
    keeps each header's frame id, seq, reason and camera gap; seq gaps are counted by `Subscriber`."""

    def __init__(self, endpoint: str, rcvhwm: int = 100_000):
        super().__init__(name="chaos-accounting", daemon=True)
        self.endpoint, self.rcvhwm = endpoint, rcvhwm
        self.frame_ids: list[int] = []
        self.seqs: list[int] = []
        self.received: list[float] = []
        self.deblurred: list[bool] = []
        self.reasons = collections.Counter()      # None = deblurred
        self.camera_gaps = 0
        self.gaps = 0
        self.gap_events: list[tuple[float, int]] = []    # (host time, frames missing before it)
        self.errors = collections.Counter()
        self.ready = threading.Event()
        self._halt = threading.Event()

    def run(self):
        with Subscriber(self.endpoint, topics=("frame",), rcvhwm=self.rcvhwm) as sub:
            self.ready.set()
            while not self._halt.is_set():
                m = sub.recv(timeout=0.1)
                if m is not None:
                    h = m[1]
                    self.frame_ids.append(int(h["frame_id"]))
                    self.seqs.append(int(h["seq"]))
                    self.received.append(h["received"])
                    self.deblurred.append(bool(h["deblurred"]))
                    self.reasons[None if h["deblurred"] else h.get("reason")] += 1
                    self.camera_gaps += int(h.get("camera_gap_before") or 0)
                if sub.gaps["frame"] != self.gaps:
                    self.gap_events.append((time.monotonic(), int(sub.gaps["frame"]) - self.gaps))
                    self.gaps = int(sub.gaps["frame"])
            self.errors.update(sub.errors)

    def count(self) -> int:
        return len(self.seqs)

    def since(self, t: float) -> tuple[int, int]:
        """Frames received at or after host time `t` (of the last 500): (all, deblurred)."""
        tail = [db for r, db in zip(self.received[-500:], self.deblurred[-500:], strict=False) if r >= t]
        return len(tail), sum(tail)

    def close(self):
        self._halt.set()
        self.join(5)


class SubscriberCrowd:
    """Stalled subscribers (connect, never read; small receive buffers so the backlog sits in the
    daemon, as with a hung client elsewhere) and subscribers that connect, read a while and leave."""

    def __init__(self, endpoint: str):
        self.endpoint = endpoint
        self.ctx = zmq.Context()
        self.stalled: list[zmq.Socket] = []
        self.churners: list[threading.Thread] = []
        self.churned = 0
        self.churn_received = 0
        self._lock = threading.Lock()

    def set_stalled(self, n: int) -> None:
        while len(self.stalled) < n:
            s = self.ctx.socket(zmq.SUB)
            s.setsockopt(zmq.RCVHWM, 1)
            s.setsockopt(zmq.RCVBUF, 1 << 16)
            s.setsockopt(zmq.LINGER, 0)
            s.setsockopt(zmq.SUBSCRIBE, b"")
            s.connect(self.endpoint)
            self.stalled.append(s)
        while len(self.stalled) > n:
            self.stalled.pop().close(linger=0)

    def churn(self, seconds: float) -> None:
        def visit():
            with Subscriber(self.endpoint, topics=("frame", "health", "gyro")) as sub:
                end, n = time.monotonic() + seconds, 0
                while time.monotonic() < end:
                    n += sub.recv(timeout=0.05) is not None
            with self._lock:
                self.churn_received += n
        th = threading.Thread(target=visit, name="chaos-churn", daemon=True)
        th.start()
        self.churners = [t for t in self.churners if t.is_alive()] + [th]
        self.churned += 1

    def close(self) -> None:
        self.set_stalled(0)
        for th in self.churners:
            th.join(5)
        self.ctx.term()


# ------------------------------------------------------------------------------------ helpers
# A subscriber that connects, then freezes (SIGSTOP: its ZeroMQ I/O thread stops reading too, like a
# hung client): `python -c FROZEN_SUBSCRIBER ENDPOINT`.
FROZEN_SUBSCRIBER = """
import os, signal, sys, time, zmq
s = zmq.Context().socket(zmq.SUB)
s.setsockopt(zmq.SUBSCRIBE, b"frame")
s.connect(sys.argv[1])
time.sleep(0.3)
os.kill(os.getpid(), signal.SIGSTOP)
"""


def rss_mb() -> float:
    """This process's resident set (VmRSS), MB."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def unit_watchdog_s(unit_file) -> float:
    """``WatchdogSec=`` of a systemd unit file, in seconds (plain, or with an ``s``/``ms``/``min`` suffix)."""
    m = re.search(r"(?m)^WatchdogSec=\s*([0-9.]+)\s*(ms|s|min)?\s*$", Path(unit_file).read_text())
    if m is None:
        raise ValueError(f"{unit_file}: no WatchdogSec= line")
    return float(m.group(1)) * {"ms": 1e-3, None: 1.0, "s": 1.0, "min": 60.0}[m.group(2)]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait(pred, timeout: float, step: float = 0.05) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(step)
    return bool(pred())


@dataclass
class _Reloads:
    good: int = 0
    applied: int = 0
    bad: collections.Counter = field(default_factory=collections.Counter)
    refused: collections.Counter = field(default_factory=collections.Counter)
    kept: int = 0                              # bad ones after which the running settings were unchanged
    problems: list = field(default_factory=list)


# ------------------------------------------------------------------------------------ the soak
def run(seconds: float = 600.0, *, seed: int = 0, method: str | None = None, workdir=None,
        watchdog_s: float = 5.0, overrides: dict | None = None, log=None) -> dict:
    """Run the daemon for `seconds` under the faults of `schedule(seconds, seed)`; return the result
    dict (see `table`). ``method``: deblur.method (None = the shipped default); ``watchdog_s``: the
    unit's WatchdogSec (the daemon pings at half of it, at most every second); ``overrides``: more
    ``{"section.key": value}`` settings, as ``thermod run --set`` (they survive reloads); ``log``: a callable
    given one line per fault (progress)."""
    say = log or (lambda line: None)
    tmp = tempfile.TemporaryDirectory(prefix="thermod-chaos-") if workdir is None else None
    work = Path(tmp.name if tmp else workdir)
    ep = f"tcp://127.0.0.1:{_free_port()}"
    overrides = {**(overrides or {}), "publish.endpoint": ep}
    if method:
        overrides["deblur.method"] = method
    cfg_path = work / "chaos.toml"
    base = configmod.default_path().read_text()
    cfg_path.write_text(base)
    cfg = configmod.load(cfg_path, overrides)
    payload = SimPayload(cfg.sim, cfg.calibration)
    payload.prepare()
    payload.start()
    gyro = HiccupGyro(payload.gyro_source())
    camera = payload.camera_source()
    notify = NotifyListener(str(work / "notify.sock"))
    notify.start()
    env = {"WATCHDOG_USEC": str(int(watchdog_s * 1e6)), "WATCHDOG_PID": str(os.getpid())}
    d = Daemon(cfg, gyro=gyro, camera=camera, notifier=Notifier(notify.path, env=env), overrides=overrides)
    acct = AccountingSubscriber(ep)          # connects before the publisher binds: sees frame seq 0
    acct.start()
    acct.ready.wait(5)
    crowd = SubscriberCrowd(ep)
    stop, reload_req = threading.Event(), threading.Event()
    serve = threading.Thread(target=d.serve, args=(stop, reload_req), name="chaos-serve", daemon=True)
    faults = collections.Counter()
    reloads = _Reloads()
    thread_deaths: set[str] = set()
    withheld = 0
    try:
        d.start()
        serve.start()
        if not _wait(lambda: d.ready, 60):
            raise RuntimeError("chaos: the daemon did not become ready within 60 s")
        time.sleep(1.0)
        rss0 = rss_mb()
        t0 = time.monotonic()
        plan = schedule(seconds, seed)
        say(f"{len(plan)} faults over {seconds:.0f} s (seed {seed})")
        i = 0
        while (now := time.monotonic() - t0) < seconds:
            while i < len(plan) and plan[i].at <= now:
                f = plan[i]
                i += 1
                faults[f.kind] += 1
                say(f"{now:7.1f} s  {f.kind} {f.arg}")
                if f.kind in RELOADS:
                    _reload(d, f, base, cfg_path, reload_req, reloads)
                else:
                    _inject(f, payload, gyro, camera, crowd)
            h = d.health()
            withheld += not all(h["threads"].values())
            thread_deaths.update(_dead_threads(d))
            time.sleep(0.2)
        # after the last fault: both devices running again and frames deblurred again (the gyro's
        # retry back-off can reach retry_max_s per failed attempt, so this may take several seconds)
        recovered = _wait(lambda: d.gyro_state.state == d.camera_state.state == "running"
                          and acct.since(time.monotonic() - 0.5)[1] > 0, 20.0, step=0.1)
        t_checked = time.monotonic()
        recovery_s = t_checked - (t0 + (plan[-1].at if plan else 0.0))
        published_quiet, deblurred_quiet = acct.since(time.monotonic() - 1.5)
        rss1 = rss_mb()
        h_end = d.health()
        alive = serve.is_alive() and all(h_end["threads"].values())
        thread_deaths.update(_dead_threads(d))
        crowd.set_stalled(0)
        # silence the camera and drain: every delivered frame is now published or counted
        camera.stall(1e6)
        drained, not_drained = _drain(d, acct)
        h = d.health()
    finally:
        stop.set()
        serve.join(5)
        d.stop()
        crowd.close()
        acct.close()
        notify.close()
        if tmp is not None:
            tmp.cleanup()
    return _result(seconds, seed, d, h, acct, crowd, faults, reloads, thread_deaths, withheld,
                   notify.longest_gap(t0, t_checked), len(notify.pings(t0)), rss0, rss1, alive,
                   published_quiet, deblurred_quiet, (drained, not_drained), watchdog_s, recovered,
                   recovery_s, t0)


def _inject(f: Fault, payload, gyro: HiccupGyro, camera, crowd: SubscriberCrowd) -> None:
    if f.kind == "gyro_unplug":
        payload.chip.unplug(f.arg)
    elif f.kind == "gyro_nack":
        payload.chip.nack(f.arg)
    elif f.kind == "fifo_overflow":
        gyro.pause(f.arg)
    elif f.kind == "clock_jump":
        gyro.jump_back(f.arg)
    elif f.kind == "camera_stall":
        camera.stall(f.arg)
    elif f.kind == "camera_disconnect":
        camera.disconnect(f.arg)
    elif f.kind == "stalled_subscribers":
        crowd.set_stalled(f.arg)
    elif f.kind == "subscriber_churn":
        crowd.churn(f.arg)
    else:
        raise ValueError(f"unknown fault kind {f.kind!r}")


def _settings(d: Daemon) -> tuple:
    c, b = d.pipeline.calib, d.pipeline.deblur
    return c.tau_s, b.lam, c.width, c.height, b.method


def _reload(d: Daemon, f: Fault, base: str, cfg_path: Path, reload_req, r: _Reloads) -> None:
    """Rewrite the config file, request a reload, wait for its outcome and check it."""
    before = _settings(d)
    n0 = d.counters["reloads"] + d.counters["reload_errors"]
    if f.kind == "reload_good":
        tau, lam = f.arg
        cfg_path.write_bytes(good_config(base, tau, lam))
        r.good += 1
    else:
        variant, seed = f.arg
        cfg_path.write_bytes(bad_config(base, variant, seed))
        r.bad[variant] += 1
    reload_req.set()
    if not _wait(lambda: d.counters["reloads"] + d.counters["reload_errors"] > n0, 5.0):
        r.problems.append(f"{f.kind} {f.arg}: no outcome within 5 s")
        return
    ok, after = d.reload_status["ok"], _settings(d)
    if f.kind == "reload_good":
        if ok and after[:2] == (tau, lam) and after[2:] == before[2:]:
            r.applied += 1
        else:
            r.problems.append(f"good reload {f.arg} not applied: ok={ok}, {d.reload_status['error']}, "
                              f"settings {after}")
    else:
        if not ok:
            r.refused[variant] += 1
        else:
            r.problems.append(f"bad reload {variant} accepted")
        if after == before:
            r.kept += 1
        else:
            r.problems.append(f"bad reload {variant} changed the settings {before} → {after}")


def _dead_threads(d: Daemon) -> set[str]:
    dead = {f"thermod-{th.kind}" for th in d.driver_threads if not th.is_alive()}
    dead |= {name for name, ok in d.pipeline.alive().items() if not ok}
    if not d.publisher.running:
        dead.add("publisher")
    return dead


def _drain(d: Daemon, acct: AccountingSubscriber, quiet_s: float = 1.0, stuck_s: float = 30.0,
           cap_s: float = 300.0) -> tuple[bool, str]:
    """Wait until the pipeline and the publisher are empty and the subscriber has stopped receiving.

    Gives up only when nothing has moved for `stuck_s` (a loaded machine works a backlog off slowly,
    so a fixed deadline would fail a pipeline that is merely behind), or after `cap_s`. Returns
    (drained, what was last not empty)."""
    def state():
        ps, pub = d.pipeline.stats(), d.publisher.stats()
        return (ps["frames_behind"], ps["job_queue_depth"], ps["pending_reorder"], pub.get("queue_depth", 0),
                acct.count())

    last, since, moved = None, time.monotonic(), time.monotonic()
    end = time.monotonic() + cap_s
    while time.monotonic() < end:
        s = state()
        now = time.monotonic()
        if s != last:
            last, since, moved = s, now, now
        elif not any(s[:4]) and now - since > quiet_s:
            return True, ""
        elif now - moved > stuck_s:
            break
        time.sleep(0.05)
    return False, ("frames behind {}, job queue {}, reorder buffer {}, publisher queue {}, "
                   "subscriber count {}".format(*last))


def _result(seconds, seed, d, h, acct, crowd, faults, reloads, thread_deaths, withheld, wd_gap, wd_pings,
            rss0, rss1, alive, published_quiet, deblurred_quiet, drain, watchdog_s, recovered,
            recovery_s, t0) -> dict:
    pc = h["pipeline"]["counters"]
    drops = h["drops"]
    drained, not_drained = drain
    written = d.camera_state.items
    rejected = int(drops.get("camera_items_rejected", 0))
    delivered = written + rejected
    pub = d.publisher.stats()
    # published = handed to ZeroMQ by the publisher; what it did not send (hand-off queue overflow,
    # byte budget, a header it could not encode) is named only as far as its counters cover it
    published, queued = int(pub["sent"]["frame"]), int(pub["queued"]["frame"])
    pub_counted = (int(pub.get("budget_dropped", {}).get("frame", 0)) + int(pub.get("queue_dropped", 0))
                   + int(pub.get("send_errors", 0)))
    named = {"frames_overrun": int(pc.get("frames_overrun", 0)), "camera_items_rejected": rejected,
             "emit_errors": int(pc.get("emit_errors", 0)),
             "publisher_dropped": min(queued - published, pub_counted)}
    in_flight = written - int(pc.get("frames_out", 0)) - named["frames_overrun"]
    unaccounted = delivered - published - sum(named.values())
    # the accounting subscriber: every frame sent must arrive; a sent frame that did not was dropped
    # by ZeroMQ at the per-subscriber SNDHWM (PUB drops silently: the daemon cannot count it)
    received = acct.count()
    seq_gaps = acct.gaps + (acct.seqs[0] if acct.seqs else 0)       # frames the subscriber never saw
    ids = acct.frame_ids
    duplicates = len(ids) - len(set(ids))
    span = max(ids) - min(ids) + 1 if ids else 0
    passthrough = {k.removeprefix("passthrough_"): int(v) for k, v in pc.items()
                   if k.startswith("passthrough_")}
    deblurred = acct.reasons.get(None, 0)
    return {
        "seconds": seconds, "seed": seed, "method": d.pipeline.deblur.method,
        "faults": dict(faults), "faults_total": sum(faults.values()),
        "reloads": {"good": reloads.good, "applied": reloads.applied, "bad": dict(reloads.bad),
                    "refused": dict(reloads.refused), "bad_total": sum(reloads.bad.values()),
                    "refused_total": sum(reloads.refused.values()), "kept_settings": reloads.kept,
                    "problems": reloads.problems, "final": dict(d.reload_status)},
        "frames": {"camera_lost": int(drops.get("camera_frames_lost", 0)),
                   "sensor": delivered + int(drops.get("camera_frames_lost", 0)),
                   "delivered": delivered, "published": published, "dropped": named,
                   "in_flight": in_flight, "drained": drained, "not_drained": not_drained,
                   "unaccounted": unaccounted,
                   "received": received, "wire_lost": published - received,
                   "wire_gaps_at_s": [(round(t - t0, 1), n) for t, n in acct.gap_events[:20]],
                   "seq_gaps": seq_gaps, "duplicates": duplicates, "ids_spanned": span,
                   "ids_missing": span - len(set(ids)),
                   "ids_unexplained": span - len(set(ids)) - int(drops.get("camera_frames_lost", 0))
                   - sum(named.values()) - (published - received),
                   "subscriber_errors": dict(acct.errors)},
        "passthrough": passthrough,
        "published_by_reason": {("deblurred" if k is None else k): v for k, v in acct.reasons.items()},
        "deblurred_share": deblurred / received if received else 0.0,
        "rss_mb": {"start": round(rss0, 1), "end": round(rss1, 1), "growth": round(rss1 - rss0, 1)},
        "threads": {"deaths": len(thread_deaths) + int(pc.get("workers_replaced", 0)),
                    "dead": sorted(thread_deaths), "workers_replaced": int(pc.get("workers_replaced", 0)),
                    "watchdog_withheld_samples": withheld},
        "watchdog": {"pings": wd_pings, "longest_gap_s": round(wd_gap, 3), "watchdog_sec": watchdog_s},
        "end": {"alive": alive, "recovered": recovered, "recovery_s": round(recovery_s, 2),
                "published_last_1.5s": published_quiet,
                "deblurred_last_1.5s": deblurred_quiet,
                "gyro": h["devices"]["gyro"]["state"], "camera_restarts": d.camera_state.restarts,
                "gyro_outages": d.counters["gyro_outages"]},
        "subscribers": {"churned": crowd.churned, "churn_received": crowd.churn_received,
                        "publisher": {k: pub[k] for k in ("queue_dropped", "budget_dropped", "send_errors",
                                                          "held_peak_bytes", "hwm") if k in pub}},
        "drops": {k: v for k, v in drops.items() if v},
    }


def table(r: dict) -> str:
    """The result as a plain-text table (markdown-compatible)."""
    f, rl, th, wd = r["frames"], r["reloads"], r["threads"], r["watchdog"]
    rows = [("soak", f"{r['seconds']:.0f} s, seed {r['seed']}, deblur.method {r['method']}"),
            ("faults injected", f"{r['faults_total']}: " + _pairs(r["faults"])),
            ("reloads good: applied", f"{rl['applied']}/{rl['good']}"),
            ("reloads bad: refused (settings kept)",
             f"{rl['refused_total']}/{rl['bad_total']} ({rl['kept_settings']} kept): "
             + ", ".join(f"{k} {rl['refused'].get(k, 0)}/{v}" for k, v in sorted(rl["bad"].items()))),
            ("camera frames read", f"{f['sensor']} = delivered {f['delivered']} + lost in the camera "
                                   f"{f['camera_lost']} (camera_frames_lost)"),
            ("delivered = published + dropped", f"{f['delivered']} = {f['published']} published"
             + "".join(f" + {v} {k}" for k, v in f["dropped"].items() if v)),
            ("frame ids missing from the stream", f"{f['ids_missing']} of {f['ids_spanned']}; not camera "
                                                  f"losses or drops: {f['ids_unexplained']}"),
            ("unaccounted", f"{f['unaccounted']}"
             + ("" if f["drained"] else f" (pipeline not drained: {f['not_drained']})")),
            ("accounting subscriber: received", f"{f['received']} of {f['published']} published; seq gaps "
                                                f"{f['seq_gaps']}, duplicate ids {f['duplicates']}"
             + (f"; lost on the wire (ZeroMQ HWM, uncounted) {f['wire_lost']} at "
                + ", ".join(f"{t} s ({n})" for t, n in f["wire_gaps_at_s"]) if f["wire_lost"] else "")),
            ("published: deblurred share", f"{r['deblurred_share']:.1%}"),
            ("passthrough reasons", _pairs(r["passthrough"]) or "none"),
            ("RSS start → end (MB)", f"{r['rss_mb']['start']:.0f} → {r['rss_mb']['end']:.0f} "
                                     f"({r['rss_mb']['growth']:+.0f})"),
            ("thread deaths", f"{th['deaths']}" + (f" ({', '.join(th['dead'])})" if th["dead"] else "")
             + f"; watchdog withheld in {th['watchdog_withheld_samples']} samples"),
            ("watchdog pings: longest gap", f"{wd['longest_gap_s']:.2f} s over {wd['pings']} pings "
                                            f"(WatchdogSec {wd['watchdog_sec']:g})"),
            ("at the end", f"alive {r['end']['alive']}; "
                           + (f"deblurring again {r['end']['recovery_s']:.1f} s after the last fault, "
                              if r["end"]["recovered"] else "NOT deblurring again, ")
                           + f"{r['end']['published_last_1.5s']} frames published in the last 1.5 s"),
            ("subscribers that came and left", f"{r['subscribers']['churned']}")]
    if rl["problems"]:
        rows.append(("reload problems", "; ".join(rl["problems"])))
    w = max(len(k) for k, _ in rows)
    return "\n".join(f"| {k:<{w}} | {v} |" for k, v in rows)


def _pairs(d: dict) -> str:
    return ", ".join(f"{k} {v}" for k, v in sorted(d.items()))

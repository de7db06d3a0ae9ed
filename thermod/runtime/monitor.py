"""The live calibration monitor (``[monitor]``): a low-priority thread that estimates the gyro bias,
time offset and τ from the stream (`thermod.calib.live`) and, with ``apply = true``, applies a change.

It reads the rings the driver threads write (never the pipeline's queue): each pair of consecutive
frames, once the gyro covers it, is registered against the gyro (in order, skipping ahead when it
falls behind); every second the rolling window is fitted. Frames flagged ffc, or after a camera
gap, and gyro windows with a gap are skipped.

The rules it keeps: frames come first. The thread runs at nice 19 and after each piece of work of
CPU time c sleeps c·(1/cpu_share − 1), so it uses at most ``cpu_share`` of one core; while the
pipeline is short of CPU (`short_of_cpu`) it does no work at all (``yielded_s``). Once
``stable_windows`` fits in a row agree with the calibration in force it is settled: it watches for
drift with ``settled_cpu_share``, its window and fit period stretched by the shares' ratio, until a
fit departs (`_settle`). The windows keep two fits' worth of pairs (a slow host lengthens them). τ uses
at most `TAU_CPU_SHARE` of the thread's CPU, on pairs drawn at random (`TAU_PICK`). A window whose
bias and offset are confounded (`Estimate.ambiguous`) is never applied; otherwise a change must lie
``k_sigma`` σ from the calibration in force in ``stable_windows`` consecutive, mutually agreeing fits
and lower its own residual on the window (the registration residual for bias and offset, the
tail-phase misfit for τ). Each change is logged, counted and applied by the daemon through
`Pipeline.update` (`take_proposal`); a τ change re-centres the τ scan. A SIGHUP reload puts the
configuration's (or a recording's) calibration back in force. In full: docs/design.md §6.
"""

from __future__ import annotations

import collections
import logging
import math
import os
import random
import threading
import time

import numpy as np

from thermod.calib.live import (
    MAX_WINDOW_S,
    MIN_PAIRS,
    MIN_RESPONSE,
    MIN_TAU_PATCHES,
    TAIL_SPAN,
    TAU_REF,
    TAU_SCAN,
    TAU_WIDTH,
    GyroIntegral,
    LiveEstimator,
    Pair,
    Registrar,
    predict,
    tail_spectra,
    tail_velocity,
)
from thermod.physics.calibration import Calibration
from thermod.runtime.config import MonitorConfig
from thermod.runtime.rings import FrameRing, GyroRing

log = logging.getLogger(__name__)

FIT_PERIOD_S = 1.0
BACKLOG = 16                 # frames the monitor may lag behind the camera before it skips ahead
CPU_PERIOD_S = 10.0          # the CPU share reported is measured over about this long
TAU_CPU_SHARE = 0.25         # τ is measured with at most this share of the monitor's own CPU time
TAU_PICK = 0.5               # the chance that an affordable pair is measured for τ
GYRO_MARGIN_S = 1.0          # s of gyro history a window leaves unused at each end (tails, offset, stamps)
YIELD_S = 0.25               # while the pipeline is short of CPU the monitor checks again this often
TAU_CONFIRM = 0.15           # of τ: a fit confirms τ only this close, at CONFIRM_Z σ (a 25 % error cost
CONFIRM_Z = 2.0              # 0.9 dB on bench_monitor's τ 10/8; the σ floor is 5 %, so σ ≤ 7.5 % needed)


class Monitor:
    """One monitor thread over the daemon's rings. ``calib()`` returns the calibration in force."""

    def __init__(self, cfg: MonitorConfig, gyro_ring: GyroRing, frame_ring: FrameRing, calib,
                 short_of_cpu=None, gyro_history_s: float = MAX_WINDOW_S + 2 * GYRO_MARGIN_S):
        self.cfg, self.gyro_ring, self.frame_ring, self._calib = cfg, gyro_ring, frame_ring, calib
        # a fit needs the gyro over its whole window: a stretched window ends where the ring's history does
        # (`LiveEstimator.stretch` never shortens it below the configured window)
        self._max_window_s = min(cfg.max_window_s, gyro_history_s - 2 * GYRO_MARGIN_S)
        self._short_of_cpu = short_of_cpu or (lambda: False)
        self.estimator = LiveEstimator(cfg.window_s)
        self._registrars: dict[tuple, Registrar] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._last = None                      # the last Estimate
        self._history: collections.deque = collections.deque(maxlen=max(1, cfg.stable_windows))
        self._proposal: Calibration | None = None
        self._last_b = -1
        self._tails = None                     # (key, TailSpectra) of the last frame whose tails were made
        self._cpu_tau = 0.0                    # thread CPU time spent measuring τ, and in all
        self._cpu_all = 0.0
        self._last_fit = 0.0
        self._cpu = collections.deque()        # (wall, thread cpu) samples
        self.counters = collections.Counter()
        self._rng = random.Random()
        self.changes: list[dict] = []          # every change applied: at, before, after, residuals
        self._agreeing = 0                     # consecutive fits that agree with the calibration in force
        self.settled = False
        self._fit_windows()

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> Monitor:
        self._stop.clear()
        self._thread = threading.Thread(target=self._loop, name="thermod-monitor", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 1.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)

    # ------------------------------------------------------------------ reports
    def estimate(self) -> dict | None:
        with self._lock:
            return None if self._last is None else self._last.as_dict()

    def state(self) -> dict:
        return {"enabled": True, "apply": self.cfg.apply, "cpu_share": self.cpu_share(),
                "cpu_share_max": self._share(), "settled": self.settled,
                "pairs_in_window": len(self.estimator.pairs),
                "changes_applied": len(self.changes), **dict(self.counters)}

    def cpu_share(self) -> float | None:
        """The thread's CPU time over the wall time of the last ~10 s (share of one core)."""
        c = list(self._cpu)
        if len(c) < 2 or c[-1][0] - c[0][0] <= 0:
            return None
        return round((c[-1][1] - c[0][1]) / (c[-1][0] - c[0][0]), 4)

    def take_proposal(self) -> Calibration | None:
        """The calibration to apply now (once), or None."""
        with self._lock:
            p, self._proposal = self._proposal, None
            return p

    # ------------------------------------------------------------------ the thread
    def _loop(self) -> None:
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)   # Linux: per thread
        except (AttributeError, OSError):
            pass
        self._cpu.append((time.monotonic(), time.thread_time()))
        while not self._stop.is_set():
            if self._short_of_cpu():         # frames are being passed through: give the CPU to them
                self.counters["yielded_s"] = round(self.counters["yielded_s"] + YIELD_S, 2)
                self._stop.wait(YIELD_S)
                continue
            c0 = time.thread_time()
            try:
                worked = self._step()
            except Exception:                # the monitor must never take anything else down
                log.exception("calibration monitor: step failed")
                self.counters["errors"] += 1
                worked = True
            c1 = time.thread_time()
            self._cpu_all += c1 - c0
            now = time.monotonic()
            self._cpu.append((now, c1))
            while len(self._cpu) > 2 and now - self._cpu[1][0] > CPU_PERIOD_S:
                self._cpu.popleft()
            # the budget: idle long enough that work / (work + idle) ≤ cpu_share
            self._stop.wait((c1 - c0) * (1.0 / self._share() - 1.0) if worked else 0.01)

    def _share(self) -> float:
        """The share of one core it may use now."""
        return min(self.cfg.settled_cpu_share, self.cfg.cpu_share) if self.settled else self.cfg.cpu_share

    def _stretch(self) -> float:
        """How much sparser pairs come now than at the full share (the window and fit period grow by it)."""
        return self.cfg.cpu_share / self._share()

    def _registrar_for(self, calib: Calibration, width: int | None = None) -> Registrar:
        width = self.cfg.width if width is None else width
        key = (calib.width, calib.height, width)
        if key not in self._registrars:
            self._registrars = {k: r for k, r in self._registrars.items() if k[:2] == key[:2]}
            self._registrars[key] = Registrar(calib, width)
        return self._registrars[key]

    def _step(self) -> bool:
        """Register the next pair once the gyro covers it, fit once a second. Returns whether it worked.

        Pairs are taken in order from the frame ring while the thread keeps up; one that fell more than
        `BACKLOG` frames behind the newest jumps ahead (the frames in between are not registered)."""
        now = time.monotonic()
        worked = False
        head = self.frame_ring.head
        ib = max(self._last_b + 1, head - min(BACKLOG, self.frame_ring.capacity // 2), 1)
        if ib <= head - 1:
            worked = self._register(ib - 1, ib)
        if now - self._last_fit >= FIT_PERIOD_S * self._stretch() and len(self.estimator.pairs) > 0:
            self._last_fit = now
            self._fit()
            worked = True
        return worked

    def _current(self, calib: Calibration) -> tuple[np.ndarray, float]:
        """(bias, offset) to place patches with: the last estimate if there is one, else the calibration's."""
        with self._lock:
            e = self._last
        if e is not None:
            return np.asarray(e.bias_rad_s), e.time_offset_s
        return np.asarray(calib.bias_rad_s, float), calib.time_offset_s

    def _register(self, ia: int, ib: int) -> bool:
        calib = self._calib()
        stamp = self.frame_ring.stamp(ib)
        if stamp is None:
            self._last_b = ib
            return False
        bias, offset = self._current(calib)
        # asked until the gyro covers frame b: the frames are copied only then
        g1 = float(calib.camera_time_to_gyro(stamp[0])) + 0.01
        if not self.gyro_ring.newest_t >= g1 + abs(offset - calib.time_offset_s):
            if time.monotonic() - stamp[1] > 0.5:          # the gyro will not come (offline)
                self._last_b = ib
                self.counters["pairs_no_gyro"] += 1
            return False
        self._last_b = ib
        a = self.frame_ring.get(ia, 0.0)
        b = self.frame_ring.get(ib, 0.0)
        if not hasattr(a, "image") or not hasattr(b, "image"):
            return False
        # the comet tails of the τ scan reach TAIL_SPAN τ_max behind frame a's first row
        reach = TAIL_SPAN * TAU_SCAN[-1] * calib.tau_s + calib.readout_s
        g0 = float(calib.camera_time_to_gyro(a.t - reach)) - 0.01
        if a.ffc or b.ffc or b.gap_before:
            self.counters["pairs_skipped"] += 1
            return False
        w = self.gyro_ring.window(g0 - 0.05, g1 + 0.05, pad=2)
        if w.gap or len(w) < 4:
            self.counters["pairs_skipped"] += 1
            return True
        reg = self._registrar_for(calib)
        integ = GyroIntegral(calib, w.t, w.rate)
        cen = reg.centres
        ta, tb = np.full(len(cen), a.t), np.full(len(cen), b.t)
        pred = predict(calib, integ, ta, tb, cen, bias, offset)
        va = tail_velocity(calib, integ, ta, cen, bias, offset)
        vb = tail_velocity(calib, integ, tb, cen, bias, offset)
        da, db = reg.downsample(a.image), reg.downsample(b.image)
        shift, resp = reg.measure(da, db, pred, va, vb, calib.tau_s)
        taus = calib.tau_s * TAU_SCAN
        coherence = None
        treg = self._registrar_for(calib, min(TAU_WIDTH, self.cfg.width))
        patches = treg.tau_patches(va, vb, calib.tau_s) & (resp >= MIN_RESPONSE)
        # τ only when the motion's window is well fed: it never takes pairs bias and offset need
        affordable = self._cpu_tau <= TAU_CPU_SHARE * self._cpu_all and \
            len(self.estimator.pairs) >= 2 * MIN_PAIRS and self._rng.random() < TAU_PICK
        if patches.any() and not affordable:
            self.counters["tau_pairs_deferred"] += 1
        elif patches.any():
            c0 = time.thread_time()
            tails_a = self._tails_of(ia, a.t, calib, treg, integ, bias, offset, taus)
            tails_b = self._tails_of(ib, b.t, calib, treg, integ, bias, offset, taus)
            if treg is not reg:
                da, db = treg.downsample(a.image), treg.downsample(b.image)
            coherence = treg.tau_coherence(da, db, pred, shift, resp, tails_a, tails_b, patches)
            self.counters["tau_patch_pairs"] += int(np.isfinite(coherence[:, 0]).sum())
            self._cpu_tau += time.thread_time() - c0
        self.estimator.add(Pair(a.t, b.t, cen.copy(), shift, resp, taus, coherence))
        self.counters["pairs_registered"] += 1
        return True

    def _tails_of(self, i: int, t: float, calib: Calibration, reg: Registrar, integ: GyroIntegral,
                  bias: np.ndarray, offset: float, taus: np.ndarray):
        """Frame i's comet tails over the τ scan, reused when frame i was the last pair's frame b."""
        key = (i, calib.tau_s, tuple(np.round(bias, 9)), round(offset, 9), reg.w)
        if self._tails is not None and self._tails[0] == key:
            return self._tails[1]
        tails = tail_spectra(calib, integ, t, reg.centres, bias, offset, taus, reg.ext_f_full, TAU_REF)
        self._tails = (key, tails)
        return tails

    def _fit(self) -> None:
        span = self.estimator.span()
        if span is None:
            return
        calib = self._calib()
        g0 = float(calib.camera_time_to_gyro(span[0] - 2 * calib.tau_s - calib.readout_s)) - 0.1
        g1 = float(calib.camera_time_to_gyro(span[1])) + 0.1
        w = self.gyro_ring.window(g0, g1, pad=2)
        if len(w) < 4:
            return
        integral = GyroIntegral(calib, w.t, w.rate)
        est = self.estimator.fit(calib, integral)
        if est is None:
            return
        self.counters["fits"] += 1
        with self._lock:
            self._last = est
        self._history.append(est)
        self._settle(self._agrees(est, calib))
        if self.cfg.apply:
            self._consider(calib, est, integral)

    def _agrees(self, est, calib: Calibration) -> bool | None:
        """False when a fit departs from the calibration in force by more than ``k_sigma`` σ (bias on
        any axis, offset or τ); True when it confirms it: τ within `TAU_CONFIRM` of the τ in force at
        `CONFIRM_Z` σ. None (neither way) for an ambiguous fit, one without τ (settled before its first
        τ, a monitor would rarely measure one) and one whose τ is too uncertain to have seen an error
        that matters (τ 9.5 ± 1.2 ms is within 4 σ of 8 ms, and settled on, while the truth was 10)."""
        if est.ambiguous or est.tau_s is None or est.tau_sigma is None:
            return None
        k = self.cfg.k_sigma
        if (np.any(np.abs(est.bias_rad_s - np.asarray(calib.bias_rad_s, float)) > k * _stat(est))
                or abs(est.time_offset_s - calib.time_offset_s) > k * est.time_offset_sigma
                or abs(est.tau_s - calib.tau_s) > k * est.tau_sigma):
            return False
        if abs(est.tau_s - calib.tau_s) + CONFIRM_Z * est.tau_sigma > TAU_CONFIRM * calib.tau_s:
            return None
        return True

    def _settle(self, agrees: bool | None) -> None:
        """Settle after ``stable_windows`` agreeing fits in a row; leave on the first that departs. A
        monitor watching a calibration the stream confirms needs few pairs; one that sees a change
        needs its full share to confirm it in ``stable_windows`` fits."""
        if agrees is None:
            return
        self._agreeing = self._agreeing + 1 if agrees else 0
        settled = self._agreeing >= self.cfg.stable_windows
        if settled != self.settled:
            self.settled = settled
            self.counters["settled" if settled else "unsettled"] += 1
            self._fit_windows()

    def _fit_windows(self) -> None:
        """The estimator's windows for the share in force, holding at least a fit's worth twice over (the
        motion's up to the gyro's history): on a host too slow to register that many in ``window_s``
        (τ waits for them) they lengthen instead."""
        self.estimator.stretch(self._stretch(), keep=2 * MIN_PAIRS, max_window_s=self._max_window_s,
                               tau_keep=2 * MIN_TAU_PATCHES, max_tau_window_s=self.cfg.max_window_s)

    def _consider(self, calib: Calibration, est, integral: GyroIntegral) -> None:
        """Propose the estimate when it is significant, stable and lowers the residual. The motion
        parameters (bias, offset) and τ are judged apart: each must be significant in every one of the
        last `stable_windows` fits and agree across them, and each must lower its own residual (the
        frame-to-frame displacements for bias and offset, the comet tails' phase for τ)."""
        if len(self._history) < self.cfg.stable_windows:
            return
        hist = list(self._history)
        b_now, o_now, t_now = np.asarray(calib.bias_rad_s, float), calib.time_offset_s, calib.tau_s
        bias, offset = self._motion_change(hist, est, b_now, o_now)
        tau = self._tau_change(hist, est, t_now)
        if bias is None and tau is None:
            return
        change = {"at": time.monotonic()}
        new = {}
        if bias is not None:
            # the change as it would be applied, checked on this window against the calibration in force
            before = self.estimator.residual(calib, integral, b_now, o_now)
            after = self.estimator.residual(calib, integral, bias, offset)
            if after < before:
                new.update(bias_rad_s=tuple(float(x) for x in bias), time_offset_s=float(offset))
                change.update(bias_rad_s=[list(calib.bias_rad_s), bias.tolist()],
                              time_offset_s=[o_now, float(offset)], residual_px=[before, after])
            else:
                self.counters["proposals_refused_residual"] += 1
                log.info("calibration monitor: not applying bias %s rad/s, offset %.5f s: the residual "
                         "would not fall (%.3f → %.3f px)", np.round(bias, 5).tolist(), offset, before, after)
        if tau is not None:
            before = self.estimator.tau_misfit(calib, t_now)
            after = self.estimator.tau_misfit(calib, tau)
            if after < before:
                new.update(tau_s=float(tau))
                change.update(tau_s=[t_now, float(tau)], tau_misfit=[before, after])
            else:
                self.counters["proposals_refused_residual"] += 1
                log.info("calibration monitor: not applying tau %.5f s: the tail-phase misfit would not "
                         "fall (%.4f → %.4f)", tau, before, after)
        self._history.clear()
        if not new:
            return
        self._settle(False)          # the calibration changes: it is confirmed afresh
        log.info("calibration monitor: applying %s", "; ".join(
            f"{k} {_fmt(v[0])} → {_fmt(v[1])}" for k, v in change.items() if k != "at"))
        self.changes.append(change)
        with self._lock:
            self._proposal = calib.replace(**new)

    def _motion_change(self, hist: list, est, b_now: np.ndarray, o_now: float):
        """(bias, offset) to apply, or (None, None): significant in every fit of `hist`, stable across
        them; only the axes (and the offset) that are significant in `est` change."""
        k = self.cfg.k_sigma
        if any(e.ambiguous for e in hist):
            # a bias and a delay this window cannot tell apart (`Estimate.ambiguous`): applying either
            # would write a confounded pair into the calibration
            self.counters["proposals_refused_ambiguous"] += 1
            return None, None
        # the bias is judged by its fit's own σ: it is applied together with the offset it was fitted with,
        # so the offset's model delay error (which both share) does not count against it
        for e in hist:
            sig_b = np.abs(e.bias_rad_s - b_now) > k * _stat(e)
            sig_o = abs(e.time_offset_s - o_now) > k * e.time_offset_sigma
            if not (np.any(sig_b) or sig_o):
                return None, None
        # stable: the fits agree with the newest within their uncertainties
        for e in hist:
            s_b = np.hypot(_stat(e), _stat(est))
            s_o = math.hypot(e.time_offset_sigma, est.time_offset_sigma)
            if np.any(np.abs(e.bias_rad_s - est.bias_rad_s) > k * s_b) or \
                    abs(e.time_offset_s - est.time_offset_s) > k * s_o:
                return None, None
        # change only what is significant (an axis the motion does not reach keeps its value)
        bias = np.where(np.abs(est.bias_rad_s - b_now) > k * _stat(est), est.bias_rad_s, b_now)
        offset = est.time_offset_s if abs(est.time_offset_s - o_now) > k * est.time_offset_sigma else o_now
        return bias, offset

    def _tau_change(self, hist: list, est, t_now: float) -> float | None:
        """τ to apply, or None: estimated, significant and stable in every fit of `hist`."""
        k = self.cfg.k_sigma
        for e in hist:
            if e.tau_s is None or not abs(e.tau_s - t_now) > k * e.tau_sigma or \
                    abs(e.tau_s - est.tau_s) > k * math.hypot(e.tau_sigma, est.tau_sigma):
                return None
        return est.tau_s


def _stat(e) -> np.ndarray:
    return e.bias_sigma if e.bias_sigma_stat is None else e.bias_sigma_stat


def _fmt(v) -> str:
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    return f"{v:.5g}"

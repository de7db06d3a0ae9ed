"""The 1 Hz health message (wire topic ``health``): rates over the last period, every drop counter
under its reason, device and clock state, thread liveness, the last reload's outcome, and the
governor's state (``governor``: the method it runs now, its budget, measured costs, how often it
stepped down or up, frames per method; `thermod.runtime.governor`), and the calibration in force with
the live monitor's estimate of it (``calibration``: ``applied``, ``source``, ``estimate``).

The daemon hands `Health.message` a `Snapshot`: plain values and the two sources, nothing that
reaches back into the daemon. Sources are read through the `thermod.runtime.sources.Source` protocol
(``name``, ``clock``, ``stats()``); a driver whose ``stats()`` raises is reported, never allowed to stop
the message.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from thermod.runtime.sources import Source

# pipeline counters that are frames not deblurred or not delivered, reported under their reason
_DROP_PREFIXES = ("passthrough_", "jobs_dropped", "frames_overrun", "worker_errors", "camera_frames_lost")
_RATES = (("gyro_samples", "gyro_hz"), ("frames_in", "frames_in_hz"), ("frames_out", "frames_out_hz"),
          ("deblurred", "deblurred_hz"))


def source_stats(src: Source) -> dict:
    """The scalar entries of ``src.stats()`` (health must not die with a driver's stats)."""
    try:
        return {k: v for k, v in src.stats().items() if isinstance(v, (int, float, str, bool)) or v is None}
    except Exception as e:  # noqa: BLE001
        return {"stats_error": f"{type(e).__name__}: {e}"}


def source_clock(src: Source) -> dict | None:
    """Fit quality of the source's device-clock mapping, or None when it has none."""
    clk = src.clock
    if clk is None:
        return None
    return {"residual_std_s": _finite(clk.residual_std_s), "drift_ppm": _finite(clk.drift_ppm),
            "resets": int(clk.resets)}


# what health shows of Publisher.stats()
PUBLISHER_KEYS = ("queue_depth", "queue_dropped", "send_errors", "hwm", "held_bytes", "held_peak_bytes",
                  "budget_dropped", "warnings", "queued", "subscribed")


@dataclass(frozen=True)
class Snapshot:
    """What one health message reports, taken from the daemon at one instant."""

    pipeline: dict                 # Pipeline.stats()
    gyro_items: int                # samples / frames the driver threads delivered
    camera_items: int
    sources: dict                  # role → (Source, DeviceState.as_dict(now))
    sink_drops: dict               # "<kind>_items_rejected" → count, per driver thread
    counters: dict                 # the daemon's own counters (gyro_gaps, gyro_lost, camera_frames_lost, …)
    gyro_ring_clock_jumps: int
    gyro_ring_time_holes: int
    publisher: dict                # Publisher.stats()
    threads: dict                  # critical thread → alive
    ready: bool
    gyro_online: bool
    reload: dict
    rtsp: dict | None
    radiometry: dict
    # the calibration in force (its recording-attribute keys at the top, as `thermod record` reads them)
    # with ``applied`` (the same), ``source`` (config | recording <path> | monitor) and the live
    # monitor's ``estimate`` (`thermod.runtime.monitor`; None while it has none or is off)
    calibration: dict | None = None
    cpu: dict | None = None        # `thermod.runtime.cpu.CpuMeter.sample`: % of one core per stage


class Health:
    """Builds the health message of one daemon; keeps the totals of the previous period for rates."""

    def __init__(self) -> None:
        self._prev: dict = {}
        self.rates: dict = {name: 0.0 for _, name in _RATES}

    def _update_rates(self, totals: dict, now: float) -> None:
        dt = now - self._prev["_t"] if self._prev else None
        self.rates = {name: round((totals[k] - self._prev.get(k, 0)) / dt, 3) if dt else 0.0
                      for k, name in _RATES}
        self._prev = {**totals, "_t": now}

    def message(self, snap: Snapshot, now: float, *, update_rates: bool = False) -> dict:
        """The health message of `snap` at host time `now`; `update_rates` closes a rate period (the
        1 Hz publisher does, other callers see the last period's rates)."""
        ps = snap.pipeline
        pc = ps["counters"]
        totals = {"gyro_samples": snap.gyro_items, "frames_in": snap.camera_items,
                  "frames_out": pc.get("frames_out", 0), "deblurred": pc.get("deblurred", 0)}
        if update_rates:
            self._update_rates(totals, now)
        drops = {k: v for k, v in pc.items() if k.startswith(_DROP_PREFIXES)}
        drops.update(snap.sink_drops)
        drops.update(gyro_gaps=snap.counters.get("gyro_gaps", 0), gyro_lost=snap.counters.get("gyro_lost", 0),
                     gyro_ring_clock_jumps=snap.gyro_ring_clock_jumps,
                     gyro_ring_time_holes=snap.gyro_ring_time_holes,
                     camera_frames_lost=snap.counters.get("camera_frames_lost", 0))
        pub = snap.publisher
        drops["publish_queue_dropped"] = pub.get("queue_dropped", 0)
        drops["publish_budget_dropped"] = pub.get("budget_dropped_total", 0)
        devices, clocks = {}, {}
        for role, (src, state) in snap.sources.items():
            devices[role] = {**state, "stats": source_stats(src)}
            clk = source_clock(src)
            if clk is not None:
                clocks[role] = clk
        # flat-field corrections the pipeline saw (frames the camera flagged); their frames and those
        # of the settle time after each are under drops.passthrough_ffc
        devices["camera"]["ffc_events"] = pc.get("ffc_events", 0)
        gov = ps.get("governor") or {}
        gov = {**gov, "deblurred_by": {k.removeprefix("method_"): v for k, v in pc.items()
                                       if k.startswith("method_")}}
        return {
            "rates": dict(self.rates), "drops": drops, "devices": devices, "totals": totals, "clocks": clocks,
            "governor": gov,
            "pipeline": {k: v for k, v in ps.items() if k not in ("counters", "governor")} | {"counters": pc},
            "threads": snap.threads, "ready": snap.ready, "gyro_online": snap.gyro_online,
            # where the kernels' motion comes from: "gyro", or "video" (measured from the frames themselves)
            "motion_source": getattr(snap.sources["gyro"][0], "motion_source", "gyro"),
            # until the latency is steady (`thermod.runtime.settling`): numbers before it are cold-start ones
            "warming_up": bool(ps.get("warming_up", False)),
            "publisher": {k: pub[k] for k in PUBLISHER_KEYS if k in pub},
            "daemon": dict(snap.counters),
            "reload": dict(snap.reload),
            "rtsp": snap.rtsp,
            "radiometry": snap.radiometry,
            "calibration": snap.calibration,
            "cpu": snap.cpu or {},
        }


def status_line(h: dict, gyro_state: str, camera_state: str) -> str:
    """The one-line STATUS= for systemd."""
    r = h.get("rates", {})
    method = (h.get("governor") or {}).get("method")
    return (f"gyro {r.get('gyro_hz', 0):.0f} Hz, frames {r.get('frames_in_hz', 0):.1f} fps, "
            f"deblurred {r.get('deblurred_hz', 0):.1f} fps" + (f" ({method})" if method else "") +
            f", gyro {gyro_state}, camera {camera_state}")


def _finite(v) -> float | None:
    return None if v is None or not math.isfinite(v) else float(v)

"""The governor: degrade the deblurring method, never the share of frames deblurred.

A frame whose solve does not fit the time the machine has for it is not dropped: `Governor.choose`
picks the best rung of a ladder of methods (`ladder`: with temporal deblurring ``temporal`` →
``wiener`` → ``wiener_half``; single-frame ``kf`` → ``kf_fast`` → ``wiener``) and the finest kernel
grid, down to the frame's floor, that the predicted cost allows within the latency budget
``min(workers / fps, max_solve_s) × (1 − headroom)``, or on the floor within ``keep_s = workers /
fps × (1 − headroom)``, the longest solve the workers keep up with.

Cost: predicted = reference × L + O, with a reference per (solver family, kernel cells) timed at
warm-up (`seed`), one load factor L for the machine (`observe`: the sliding median of the key in use
over its reference) and O the median round trip around a child's solve (`overhead_s`).
Hysteresis: it steps down at once when the current rung fits neither limit, and up only to a rung
within ``(1 − margin)`` of the budget, or on its floor within ``(1 − margin)`` of ``keep_s``, ``hold_s``
after its last change; a climb undone within two holds doubles the hold (up to ``max_hold_s``).
Tail: `released` scales both limits toward the published p99 `latency_p99_s` (the latency loop);
a frame that comes late (`choose`'s `age_s`) is solved by what its predicted cost lets it finish in.

It has no clock or thread of its own: the pipeline calls `choose` (scheduler), `observe` (workers)
and `overloaded` (queue) with the host time, so tests drive it with a deterministic feed. The rules
in full: docs/design.md §6, "The governor"; the measurements: benchmarks/results/daemon.md.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import statistics
import threading
from dataclasses import dataclass

from thermod.physics.deconv.recursive import MAX_AGE_S
from thermod.physics.kernels.grids import coarser_grids
from thermod.restore.settings import DeblurConfig

log = logging.getLogger(__name__)

FAST_KF_ITERATIONS = 3            # β = 1, 8, 64: K&F's continuation at ×8 instead of ×2√2
WINDOW = 15                       # solves per key in the sliding median
MIN_SOLVES = 3                    # solves of a stretch (after its cold ones) before the key moves L
STALE_S = 1.0                     # a key unused this long starts a new stretch (its window is cleared)
NEEDED_S = 1.0                    # rungs are judged on the finest grid needed over this long
KEEP_S = 2.0                      # the keep rule's load: the median over this long of every key's solves
TAIL_FRAMES = 150                 # the latency loop judges each scale on this many released frames
TAIL_STALE_S = 20.0               # ... released within this long (a slow camera's window spans more)
TAIL_P95_SHARE = 0.75             # the p95 is held to this share of the p99 goal (45 of 60 ms)
MIN_SCALE = 0.3                   # the loop never scales the budgets below this share


@dataclass(frozen=True)
class Rung:
    """One step of the ladder: a solver (`family`) and whether it may use a kernel grid."""

    name: str                     # what frames carry in their header (`thermod.io.wire.METHODS`)
    method: str                   # kf | wiener: frame t's own solve
    kf_iterations: int | None     # None: the configuration's (K&F's six)
    varying: bool                 # may use the grid the frame needs (else uniform)
    temporal: bool = False        # the recursive temporal solve over that own solve
    coarsens: bool = False        # may coarsen the grid the frame needs when it does not fit
    half: bool = False            # solved at half resolution (`thermod.physics.deconv.half`)

    def deblur(self, base: DeblurConfig) -> DeblurConfig:
        """The DeblurConfig a worker builds this rung's deconvolver from."""
        return dataclasses.replace(base, method=self.method, kf_iterations=self.kf_iterations)


def ladder(deblur: DeblurConfig, frame_rate_hz: float | None = None) -> list[Rung]:
    """The rungs the configuration allows, best first. The temporal rung needs a camera whose frame
    period is within a prior's `MAX_AGE_S`: below ~10 fps (an export-limited 9 Hz core) no prior is
    ever young enough, and its ladder starts at ``wiener``."""
    varying = deblur.mode != "uniform"
    last = Rung("wiener", "wiener", None, varying, coarsens=True)
    half = Rung("wiener_half", "wiener", None, varying, coarsens=True, half=True)
    if deblur.temporal_views > 1 and frame_rate_hz is not None and 1.0 / frame_rate_hz > MAX_AGE_S:
        log.warning("temporal deblurring off: a frame period of %.0f ms leaves no prior within its %.0f ms "
                    "age limit; the ladder starts at wiener", 1e3 / frame_rate_hz, 1e3 * MAX_AGE_S)
        return [last, half]
    if deblur.temporal_views > 1:
        return [Rung("temporal", "wiener", None, varying, temporal=True, coarsens=True), last, half]
    if deblur.method == "wiener":
        return [last]
    rungs = [Rung("kf", "kf", deblur.kf_iterations, varying)]
    if deblur.kf_iterations is None or deblur.kf_iterations > FAST_KF_ITERATIONS:
        rungs.append(Rung("kf_fast", "kf", FAST_KF_ITERATIONS, varying))
    return [*rungs, last]


@dataclass
class Choice:
    """What the governor decided for one frame."""

    rung: Rung
    grid: tuple[int, int]         # the kernel grid to render, (1, 1) = one kernel
    index: int                    # the rung's position in the ladder (0 = best)

    @property
    def label(self) -> str:
        return self.rung.name if self.grid == (1, 1) else f"{self.rung.name} {self.grid[0]}×{self.grid[1]}"


class Governor:
    """Picks each frame's rung and grid from measured solve costs (see the module docstring).

    Parameters
    ----------
    deblur : the configured settings (method, mode, grid, max_solve_s, headroom, governor).
    frame_rate_hz, workers : the budget's frame period and worker count.
    aspect : W / H, for the coarser grids.
    hold_s, max_hold_s, margin : hysteresis (see the module docstring).
    """

    def __init__(self, deblur: DeblurConfig, frame_rate_hz: float, workers: int, aspect: float = 4 / 3, *,
                 hold_s: float = 2.0, max_hold_s: float = 32.0, margin: float = 0.25):
        self.deblur = deblur
        self.rungs = ladder(deblur, frame_rate_hz)
        self.full_last = max(i for i, r in enumerate(self.rungs) if not r.half)   # keeps its floor in keep_s
        self.last = len(self.rungs) - 1      # the rung that goes below its floor when nothing else fits
        self.enabled = bool(deblur.governor)
        self.aspect = float(aspect)
        self.budget_s = min(workers / frame_rate_hz, deblur.max_solve_s) * (1.0 - deblur.headroom)
        self.keep_s = workers / frame_rate_hz * (1.0 - deblur.headroom)   # the workers still keep up
        self.latency_goal_s = deblur.latency_p99_s
        self.scale = 1.0                # the latency loop's share of budget_s and keep_s (`released`)
        self.measured_p99_s: float | None = None    # the p99 of the last judged window
        self._released: collections.deque = collections.deque()   # (time, latency) since the last revision
        self.hold_s, self.base_hold_s, self.max_hold_s, self.margin = hold_s, hold_s, max_hold_s, margin
        self.index = 0
        self._last_change = -math.inf
        self._last_climb = -math.inf
        self._lock = threading.Lock()
        self.workers = max(1, int(workers))
        self._ref: dict[tuple[str, int], float] = {}      # (family, cells) → reference cost (s) at L = 1
        self._recent: dict[tuple[str, int], collections.deque] = {}   # this stretch's solves (s)
        self._stretch: dict[tuple[str, int], int] = {}    # solves in this stretch, the cold ones included
        self._last_seen: dict[tuple[str, int], float] = {}
        self.load = 1.0
        self._overheads: collections.deque = collections.deque(maxlen=WINDOW)   # round trips (s)
        self._ratios: collections.deque = collections.deque()   # (time, solve / its reference), KEEP_S
        self._needed: collections.deque = collections.deque()   # (time, grid, floor) of recent frames
        self._memo: dict = {}          # costs derived from the state above, cleared when it changes
        self.counts = {"degrades": 0, "climbs": 0, "failed_climbs": 0, "overload_steps": 0, "stalls": 0,
                       "tightened": 0, "relaxed": 0, "late": 0}
        self.frames: dict[str, int] = {}                   # frames per choice label

    # ------------------------------------------------------------------ costs
    @staticmethod
    def family(rung: Rung) -> str:
        """The solver a rung runs (costs are kept per family and cell count)."""
        if rung.name == "kf" and rung.kf_iterations is not None:
            return f"{rung.name}{rung.kf_iterations}"
        return rung.name

    def seed(self, family: str, cells: int, seconds: float, overhead_s: float = 0.0) -> None:
        """A key's reference cost, measured before going live (warm-up, an idle worker): the ratios
        between the keys' references are what the load factor scales; `overhead_s`, the round trip
        around that solve, seeds the overhead every prediction adds."""
        if seconds > 0 and math.isfinite(seconds):
            with self._lock:
                self._ref[family, cells] = float(seconds) / self.load
                self._add_overhead(overhead_s)
                self._memo.clear()

    def _add_overhead(self, overhead_s: float) -> None:
        if overhead_s >= 0 and math.isfinite(overhead_s):
            self._overheads.append(float(overhead_s))

    @property
    def overhead_s(self) -> float:
        """The median round trip around a solve (s): what a solve costs beyond its own work, whatever
        the work (the frame's copies, the pipe, the parent's GIL)."""
        memo = self._memo
        if "overhead" not in memo:
            memo["overhead"] = statistics.median(self._overheads) if self._overheads else 0.0
        return memo["overhead"]

    def predict(self, family: str, cells: int) -> float:
        """Predicted wall time (s) of one solve of `family` over `cells` kernel cells."""
        with self._lock:
            return self._predict(family, cells)

    def _reference(self, family: str, cells: int) -> float:
        key = (family, cells)
        if key in self._ref:
            return self._ref[key]
        if key not in self._memo:
            self._memo[key] = self._interpolated(family, cells)
        return self._memo[key]

    def _interpolated(self, family: str, cells: int) -> float:
        # never seeded: between the family's nearest references, linear in cells
        known = sorted(c for f, c in self._ref if f == family)
        if not known:
            return 0.0          # nothing known: assume it fits, the first solves will tell
        lo = max((c for c in known if c <= cells), default=known[0])
        hi = min((c for c in known if c >= cells), default=known[-1])
        rlo, rhi = self._ref[family, lo], self._ref[family, hi]
        if hi == lo:
            return rlo * cells / lo
        return rlo + (rhi - rlo) * (cells - lo) / (hi - lo)

    def _predict(self, family: str, cells: int, load: float | None = None) -> float:
        """The predicted cost (s) of a solve over `cells` kernel cells: reference × load + overhead, at
        the load factor or `load`."""
        return self._reference(family, cells) * (self.load if load is None else load) + self.overhead_s

    def observe(self, family: str, cells: int, seconds: float, now: float, overhead_s: float = 0.0) -> None:
        """A worker's measured solve time (s; the solve itself) and the round trip around it, at host
        time `now`."""
        if not (seconds > 0 and math.isfinite(seconds)):
            return
        with self._lock:
            self._memo.clear()
            self._add_overhead(overhead_s)
            key = (family, cells)
            if key not in self._recent or now - self._last_seen.get(key, -math.inf) > STALE_S:
                self._recent[key] = collections.deque(maxlen=WINDOW)
                self._stretch[key] = 0
            self._last_seen[key] = now
            self._stretch[key] += 1
            if self._stretch[key] <= self.workers:        # each worker's first solve of the stretch: cold
                return
            recent = self._recent[key]
            recent.append(float(seconds))
            if len(recent) < MIN_SOLVES:
                return
            med = statistics.median(recent)
            ref = self._reference(family, cells)
            if key not in self._ref:
                if ref <= 0:                               # a family never seeded: learn it at today's L
                    self._ref[key] = med / self.load
                    return
                self._ref[key] = ref                       # interpolated: fixed from now on
            self.load = med / self._ref[key]
            ratios = self._ratios
            ratios.append((now, float(seconds) / self._ref[key]))
            while ratios and ratios[0][0] < now - KEEP_S:
                ratios.popleft()

    def inherit(self, old: Governor) -> None:
        """Keep what `old` measured (a reload with new deblur settings keeps the machine's costs)."""
        with old._lock:
            refs, load, scale = dict(old._ref), old.load, old.scale
        with self._lock:
            self._ref, self.load, self.scale = refs, load, scale
            self._memo.clear()

    # ------------------------------------------------------------------ the latency loop
    @property
    def limit_s(self) -> float:
        """The solve budget the decisions use: `budget_s` times the latency loop's scale."""
        return self.budget_s * self.scale

    @property
    def keep_limit_s(self) -> float:
        """The keep rules' limit: `keep_s` times the latency loop's scale."""
        return self.keep_s * self.scale

    def released(self, latency_s: float, now: float) -> None:
        """A deblurred frame was published `latency_s` after its read (host time `now`).

        The predictions budget a solve's median; the published tail also holds the queue and the
        host's slow solves. Every `TAIL_FRAMES` frames the loop compares the window's p99 with the
        goal and its p95 with `TAIL_P95_SHARE` of it, r the larger ratio: r > 1 scales both budgets
        by 1/r (at most ×0.75 a step, down to `MIN_SCALE`); r < 1 − margin scales them ×1.15, up to 1.
        Each scale is judged on frames solved under it (the window starts again)."""
        if not self.enabled or not (latency_s >= 0 and math.isfinite(latency_s)):
            return
        with self._lock:
            window = self._released
            window.append((now, float(latency_s)))
            while window and window[0][0] < now - TAIL_STALE_S:
                window.popleft()
            if len(window) < TAIL_FRAMES:
                return
            q = statistics.quantiles((x for _, x in window), n=100, method="inclusive")
            window.clear()
            self.measured_p99_s = q[98]
            r = max(q[98] / self.latency_goal_s, q[94] / (TAIL_P95_SHARE * self.latency_goal_s))
            if r > 1.0 and self.scale > MIN_SCALE:
                self.scale = max(MIN_SCALE, self.scale * max(0.75, 1.0 / r))
                self.counts["tightened"] += 1
            elif r < 1.0 - self.margin and self.scale < 1.0:
                self.scale = min(1.0, self.scale * 1.15)
                self.counts["relaxed"] += 1

    # ------------------------------------------------------------------ decisions
    def _grids(self, i: int, needed: tuple[int, int], floor: tuple[int, int],
               beyond_floor: bool = False) -> list[tuple[int, int]]:
        """The grids rung i may solve a frame needing `needed` with, finest first: `needed` itself, or
        (a coarsening rung) the coarser ones too, down to `floor` (`beyond_floor`: to one kernel)."""
        r = self.rungs[i]
        if not r.varying:
            return [(1, 1)]
        if not r.coarsens:
            return [needed]
        grids = coarser_grids(needed, self.aspect)
        if beyond_floor:
            return grids
        return [g for g in grids if g[0] * g[1] >= floor[0] * floor[1]] or [needed]

    def _fits(self, i: int, needed: tuple[int, int], limit: float, floor: tuple[int, int] = (1, 1),
              beyond_floor: bool = False) -> tuple[int, int] | None:
        """The grid rung i solves a frame needing `needed` with, if its predicted cost is within
        `limit`, else None: `needed` itself (a coarsening rung: the finest grid of `_grids` that fits)."""
        r = self.rungs[i]
        fam = self.family(r)
        for g in self._grids(i, needed, floor, beyond_floor):
            if self._predict(fam, g[0] * g[1]) <= limit:
                return g
        return None

    def _pick(self, i: int, needed: tuple[int, int], floor: tuple[int, int]) -> tuple[int, int] | None:
        """The grid rung i solves this frame with, or None: within the budget down to the floor; on
        its floor within `keep_s` (the rung in use and the last full-resolution one; not the
        half-resolution rung, the last resort, which keeps to the budget); the last rung
        then beyond its floor within the budget, and, when it is a full-resolution one (no
        half-resolution rung below), within `keep_s`. The latency loop scales every limit. Below the
        floor the half-resolution rung comes before full resolution: over its floor it restores
        about what full resolution does there, and far more than one full-resolution kernel
        (benchmarks/results/payload.md, "Half resolution over a grid")."""
        g = self._fits(i, needed, self.limit_s, floor)
        if g is None and i in (self.index, self.full_last) and not self.rungs[i].half:
            g = self._keeps(i, needed, floor)
        if g is None and i == self.last:
            g = self._fits(i, needed, self.limit_s, floor, True)
            if g is None and not self.rungs[i].half:
                g = self._keeps_beyond_floor(i, needed)
        return g

    def _keeps_beyond_floor(self, i: int, needed: tuple[int, int]) -> tuple[int, int] | None:
        """The last rung at full resolution with none below it (the single-frame ladder's Wiener),
        when nothing fits the budget: the finest grid, down to one kernel, predicted within `keep_s`
        (scaled by the latency loop)."""
        return next((g for g in self._grids(i, needed, (1, 1), True)
                     if self._keep_cost(i, g) <= self.keep_limit_s), None)

    def _keeps(self, i: int, needed: tuple[int, int], floor: tuple[int, int], limit: float | None = None
               ) -> tuple[int, int] | None:
        """The coarsest grid rung i, a coarsening rung, keeps when none fits the budget: its floor (the
        grid within ``temporal_tol_px``), if its solve there is predicted within `keep_s` (the workers
        keep up with the frame rate) at the load of the last `KEEP_S` (a burst shorter than about half
        of it moves that median little). None: a rung above the last gives its method up, the last
        its floor (`choose`). `limit`: keep_s unless given (a climb back asks for a margin below it)."""
        if not self.rungs[i].coarsens:
            return None
        g = self._grids(i, needed, floor)[-1]
        return g if self._keep_cost(i, g) <= (self.keep_limit_s if limit is None else limit) else None

    def _keep_cost(self, i: int, grid: tuple[int, int]) -> float:
        """Rung i's predicted cost over `grid` for the keep rules: at the load of the last `KEEP_S`."""
        return self._predict(self.family(self.rungs[i]), grid[0] * grid[1], self._keep_load())

    def _keep_load(self) -> float:
        """The median load of the last `KEEP_S` of solves (the load factor until there are enough)."""
        memo = self._memo
        if "keep_load" not in memo:
            memo["keep_load"] = statistics.median(x for _, x in self._ratios) \
                if len(self._ratios) >= MIN_SOLVES else self.load
        return memo["keep_load"]

    def _recent_grids(self) -> tuple[tuple[int, int], tuple[int, int]]:
        """(the finest grid needed, the median floor) over the last `NEEDED_S`: rungs are judged on
        both. On the median floor, frames whose roll asks for a finer one than the rung affords go to
        the next rung one by one (`choose`), not the whole stream."""
        cells = lambda g: g[0] * g[1]  # noqa: E731
        worst = max((g for _, g, _ in self._needed), key=cells, default=(1, 1))
        floors = sorted((f for _, _, f in self._needed), key=cells) or [(1, 1)]
        return worst, floors[len(floors) // 2]

    def choose(self, needed: tuple[int, int], now: float, floor: tuple[int, int] = (1, 1),
               age_s: float = 0.0) -> Choice:
        """The rung and grid for a frame whose blur needs the grid `needed` ((1, 1): uniform); a
        coarsening rung coarsens it no further than `floor` (the grid within ``temporal_tol_px``)
        while the workers keep up there, the last rung beyond it only as a last resort. `age_s`: how
        long ago the frame arrived (`_in_time`)."""
        with self._lock:
            if not self.enabled:
                r = self.rungs[0]
                return Choice(r, needed if r.varying else (1, 1), 0)
            recent = self._needed
            recent.append((now, tuple(needed), tuple(floor)))
            while recent and recent[0][0] < now - NEEDED_S:
                recent.popleft()
            worst, worst_floor = self._recent_grids()
            if self._pick(self.index, worst, worst_floor) is None:        # over budget: step down now
                i = self.index + 1
                while i < self.last and self._pick(i, worst, worst_floor) is None:
                    i += 1
                if i <= self.last:
                    self._move(i, now)
            elif self.index > 0 and now - self._last_change >= self.hold_s:
                budget, keep = self.limit_s * (1 - self.margin), self.keep_limit_s * (1 - self.margin)
                for i in range(self.index):                       # best rung that fits with margin
                    if self._fits(i, worst, budget, worst_floor) is not None \
                            or self._keeps(i, worst, worst_floor, keep) is not None:
                        self._move(i, now)
                        break
            i = self.index
            g = self._pick(i, needed, floor)
            while g is None and i < self.last:                        # this frame only: a cheaper rung
                i += 1
                g = self._pick(i, needed, floor)
            i, g = self._in_time(i, g or (1, 1), needed, floor, age_s)
            c = Choice(self.rungs[i], g, i)
            self.frames[c.label] = self.frames.get(c.label, 0) + 1
            return c

    def _in_time(self, i: int, g: tuple[int, int], needed: tuple[int, int], floor: tuple[int, int],
                 age_s: float) -> tuple[int, tuple[int, int]]:
        """Rung i over grid g, unless a frame that came `age_s` ago would end its solve past ``(1 − margin)``
        of the p99 goal (predicted, the queue left out): then the best rung from i down, and grid down
        to the floor (the last rung beyond it), predicted within what is left, else the last rung over
        one kernel. A late frame (a long wait for its motion, a stalled host) is the tail the loop
        would otherwise answer by cheapening every frame."""
        left = self.latency_goal_s * (1.0 - self.margin) - age_s
        if not (self.enabled and age_s > 0 and math.isfinite(left)) or \
                self._predict(self.family(self.rungs[i]), g[0] * g[1]) <= left:
            return i, g
        self.counts["late"] += 1
        for j in range(i, self.last + 1):
            gj = self._fits(j, needed, left, floor, beyond_floor=j == self.last)
            if gj is not None:
                return j, gj
        return self.last, (1, 1)

    def overloaded(self, now: float) -> None:
        """A job was dropped for overload. When the current rung's predicted cost (over the finest
        grid needed lately) is above the climb threshold, ``(1 − margin)`` of the budget, the
        predictions were too low: step down one rung now. Below it the rung left the workers most of
        their time, so the queue overflowed because the cores were taken away for a while (a stall:
        counted in ``stalls``) and a cheaper method would not have kept the frame: the rung stays
        (the measured solve times move the load factor if the machine stays slower)."""
        with self._lock:
            if not self.enabled or self.index >= self.last:
                return
            worst, floor = self._recent_grids()
            if self._fits(self.index, worst, self.limit_s * (1 - self.margin), floor) is not None:
                self.counts["stalls"] += 1
                return
            self.counts["overload_steps"] += 1
            self._move(self.index + 1, now)

    def _move(self, i: int, now: float) -> None:
        if i == self.index:
            return
        if now - self._last_change > 4 * self.max_hold_s:           # long stable: forgive old failures
            self.hold_s = self.base_hold_s
        if i > self.index:
            self.counts["degrades"] += 1
            if now - self._last_climb < 2 * self.hold_s:          # the last climb did not hold
                self.counts["failed_climbs"] += 1
                self.hold_s = min(self.max_hold_s, 2 * self.hold_s)
        else:
            self.counts["climbs"] += 1
            self._last_climb = now
        self.index = i
        self._last_change = now

    # ------------------------------------------------------------------ health
    def state(self) -> dict:
        """For health: the current rung, budget, predictions and counters."""
        with self._lock:
            return {
                "enabled": self.enabled,
                "method": self.rungs[self.index].name,
                "rung": self.index,
                "ladder": [r.name for r in self.rungs],
                "budget_ms": round(1e3 * self.limit_s, 2),
                "latency_scale": round(self.scale, 3),
                "latency_goal_ms": round(1e3 * self.latency_goal_s, 1),
                "latency_p99_ms": None if self.measured_p99_s is None
                else round(1e3 * self.measured_p99_s, 1),
                "load": round(self.load, 3),
                "overhead_ms": round(1e3 * self.overhead_s, 2),
                "keep_load": round(self._keep_load(), 3),
                "hold_s": self.hold_s,
                "cost_ms": {f"{f}×{c}": round(1e3 * self._predict(f, c), 2) for f, c in sorted(self._ref)},
                "solves_measured": sum(len(d) for d in self._recent.values()),
                "frames": dict(self.frames),
                **self.counts,
            }

"""A chaos soak: the daemon, in-process on the simulated payload, for N minutes under random faults (a
gyro unplug/NACK/FIFO overflow, a camera stall/disconnect, a clock jump, a good or bad SIGHUP reload,
stalled or churning subscribers: one every 1–3 s; see `thermod.chaos`). Prints a table: every
camera frame published or counted under a reason, passthrough reasons, RSS at start and end, thread
deaths, the longest gap between watchdog pings, faults by kind and reloads applied/refused.

    .venv/bin/python -m benchmarks.bench_chaos [--minutes 10] [--seed 0] [--method kf] [--set K=V] [--quick]

Targets: unaccounted 0, nothing lost on the wire to a subscriber that keeps up, thread deaths 0,
every bad reload refused and every good one applied, longest watchdog gap < WatchdogSec
(systemd/thermod.service), RSS growth < 200 MB. Exit 1 if one is missed.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from thermod import chaos
from thermod.runtime import config

REPO = Path(__file__).resolve().parents[1]
RSS_GROWTH_MB = 200


def misses(r: dict, watchdog_s: float) -> list[str]:
    f, rl = r["frames"], r["reloads"]
    out = []
    if f["unaccounted"] or not f["drained"]:
        out.append(f"{f['unaccounted']} frames unaccounted (drained: {f['drained']})")
    if f["wire_lost"]:
        out.append(f"{f['wire_lost']} frames sent but lost on the way to the accounting subscriber "
                   f"(ZeroMQ SNDHWM; the daemon cannot count them) at {f['wire_gaps_at_s']}")
    if r["threads"]["deaths"]:
        out.append(f"thread deaths: {r['threads']}")
    if rl["problems"]:
        out.append(f"reloads: {rl['problems']}")
    if r["watchdog"]["longest_gap_s"] >= watchdog_s:
        out.append(f"watchdog gap {r['watchdog']['longest_gap_s']} s ≥ WatchdogSec {watchdog_s}")
    if r["rss_mb"]["growth"] >= RSS_GROWTH_MB:
        out.append(f"RSS grew {r['rss_mb']['growth']} MB")
    if not (r["end"]["alive"] and r["end"]["published_last_1.5s"]):
        out.append(f"not publishing at the end: {r['end']}")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--method", default=None, help="deblur.method (default: the shipped configuration's)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a configuration override, as `thermod run --set` (repeatable)")
    ap.add_argument("--quick", action="store_true", help="1 minute, Wiener")
    ap.add_argument("--json", type=Path, help="also write the result dict here")
    ap.add_argument("-v", "--verbose", action="store_true", help="print each fault as it is injected")
    args = ap.parse_args(argv)
    if args.quick:
        args.minutes, args.method = 1.0, args.method or "wiener"
    logging.basicConfig(level=logging.ERROR, format="%(levelname)s %(name)s: %(message)s")
    watchdog_s = chaos.unit_watchdog_s(REPO / "systemd" / "thermod.service")
    overrides = dict(config.parse_override(x) for x in args.set)
    r = chaos.run(args.minutes * 60.0, seed=args.seed, method=args.method, watchdog_s=watchdog_s,
                  overrides=overrides, log=print if args.verbose else None)
    if overrides:
        print("overrides:", overrides)
    print(chaos.table(r))
    if args.json:
        args.json.write_text(json.dumps(r, indent=1, default=str))
    bad = misses(r, watchdog_s)
    for m in bad:
        print("MISSED:", m, file=sys.stderr)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())

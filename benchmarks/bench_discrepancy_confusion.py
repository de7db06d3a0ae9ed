"""Confusion table of the motion-only discrepancy search on flights from three real logs (issue 34).

Each case renders a flight with the simulator's fine-time renderer on a stretch of a real log, every one
with roll, no static lead-in, NETD 50 mK, 640×480, analysed motion-only at work width 160 with every
candidate, and records what was named, what was reported `ambiguous` (`identify`) and what was named
wrongly. Logs (../shared/data, SOURCES.md): the Betaflight 2 kHz CSV the search was tuned on
(`bf2k`, from 27 s: no test or other benchmark uses that stretch), the Betaflight 4.2 blackbox at
~1 kHz (`bf42`, from 2 s) and the PX4 ULog at 250 Hz moved by hand (`px4`, from 2.5 s); 0.8 s and 3 s
flights from the same start. Hidden: each timing effect alone, and the offset + readout pair.

A truth effect counts as **named** when the search names it within issue 6's tolerance (offset ±1 ms,
readout ±20 %, bias ±0.3 °/s on each axis it resolved, τ ±10 %; a bias axis within its resolution of
nominal is held there and reported `unresolved`, and the verdict says so), **ambiguous** when it is in
an `ambiguous` entry, **below resolution** when nothing timing was named, the report states what the
flight resolves, and the whole hidden change raises the SSR by less than `min_gain` in that curvature
(no fit could remove enough to name it from this motion), else
**missed**; every named effect that is not hidden is a **wrong name**.

    .venv/bin/python -m benchmarks.bench_discrepancy_confusion [--cases LOG:SECONDS:EFFECT,...]
        [--out benchmarks/results/discrepancy_heldout.md]

Prints a row per case as it ends, then the confusion table over every case measured so far. Results
are kept one JSON line per case in benchmarks/results/discrepancy_heldout.jsonl (a case already there
is not run again; delete its line to measure it anew), so the cases can run as separate processes;
`--out` writes the table into the results file's confusion section (`--cases ""` writes what is
cached). `--list` prints the case names. Each case costs minutes of CPU, a 3 s flight several times a
0.8 s one (the table's CPU s column).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("NUMBA_CACHE_DIR", str(Path(__file__).resolve().parents[1] / ".numba_cache"))

import numpy as np  # noqa: E402

from thermod.calib import discrepancy as D  # noqa: E402
from thermod.calib.discrepancy import identify  # noqa: E402
from thermod.sim.flight_recordings import flight_recording  # noqa: E402
from thermod.sim.scenes import shared_data_dir  # noqa: E402

DEG = math.pi / 180
SIZE, WORK_WIDTH = (640, 480), 160
# name: (path under shared/data, or None for the Betaflight CSV; start s)
LOGS = {"bf2k": (None, 27.0), "bf42": ("logs/betaflight_4.2_LOG00037.BFL", 2.0),
        "px4": ("logs/px4_sample.ulg", 2.5)}
EFFECTS = {
    "time_offset": {"time_offset": 0.006},
    "rolling_readout": {"rolling_readout": 0.015},
    "gyro_bias": {"gyro_bias": (0.03, -0.02, 0.015)},
    "time_constant": {"time_constant": 0.012},
    "time_offset+rolling_readout": {"time_offset": -0.005, "rolling_readout": 0.010},
}
SECONDS = (0.8, 3.0)
TIMING = ("time_offset", "rolling_readout", "gyro_bias", "time_constant")
RESULTS = Path(__file__).resolve().parent / "results" / "discrepancy_heldout.jsonl"
SECTION = "## Confusion table: flights from three logs (issue 34)"


def case_names() -> list[str]:
    return [f"{log}:{s:g}:{e}" for s in SECONDS for e in EFFECTS for log in LOGS]


def within(effect: str, c, t, unresolved=()) -> bool:
    """Issue 6's tolerance for `effect` (fitted calibration c, truth t), on the bias axes the search
    resolved (`unresolved`: the parameter names it held at nominal and said so)."""
    if effect == "time_offset":
        return abs(c.time_offset_s - t.time_offset_s) < 1e-3
    if effect == "rolling_readout":
        return abs(c.readout_s - t.readout_s) < 0.2 * t.readout_s
    if effect == "gyro_bias":
        names = [label for effect, label, _ in identify.PARAMS if effect == "gyro_bias"]
        axes = [i for i, p in enumerate(names) if p not in unresolved]
        return bool(np.all(np.abs(np.subtract(c.bias_rad_s, t.bias_rad_s))[axes] < 0.3 * DEG))
    if effect == "time_constant":
        return abs(c.tau_s / t.tau_s - 1) < 0.10
    return True


def run_case(name: str, data: Path) -> dict:
    log, seconds, effect = name.split(":")
    rel, start = LOGS[log]
    c0 = time.process_time()
    fr = flight_recording(EFFECTS[effect], seconds=float(seconds), size=SIZE, real_log=True,
                          log_start_s=start, log=None if rel is None else data / rel)
    d = D.prepare(fr.rec, fr.nominal, name=name, work_width=WORK_WIDTH)
    ana = D.analyse([d], D.Model(fr.nominal))
    hidden = effect.split("+")
    c, t, c_nom = ana.model.calib, fr.truth, fr.nominal
    ident = ana.identifiability
    rho = ident.get("correlation")
    unresolved = [u["param"] for u in ident.get("unresolved", [])]
    # what the report says the flight resolves: the identifiability check's, else the one at the final model
    res = (dict(zip(ident["params"], ident["resolution"], strict=True)) if ident else
           {k: v["resolution"] for k, v in ana.resolution.get("parameters", {}).items()})
    # the hidden change, all of it at once, in the curvature the report states (units of min_gain)
    delta = np.subtract([t.time_offset_s, t.readout_s, *t.bias_rad_s, t.tau_s],
                        [c_nom.time_offset_s, c_nom.readout_s, *c_nom.bias_rad_s, c_nom.tau_s])
    rise = float(delta @ np.array(ana.resolution["rise"]) @ delta) if ana.resolution else None
    return {
        "case": name, "hidden": hidden, "named": ana.named, "ambiguous": ana.ambiguous_effects,
        "ambiguous_labels": [a["label"] for a in ana.ambiguous],
        "wrong": [n for n in ana.named if n not in hidden],
        "within": {h: within(h, c, t, unresolved) for h in hidden if h in ana.named},
        "unresolved": unresolved,
        "sigma": dict(zip(ident["params"], ident["sigma"], strict=True)) if ident else None,
        "resolution": res or None,
        "hidden_rise": rise,
        "below_resolution": {h: rise is not None and rise < 1.0 for h in hidden},
        "values": {"time_offset_ms": 1e3 * c.time_offset_s, "readout_ms": 1e3 * c.readout_s,
                   "bias_deg_s": [v / DEG for v in c.bias_rad_s], "tau_ms": 1e3 * c.tau_s},
        "sigma_readout_ms": 1e3 * ident["sigma"][1] if ident else None,
        "resolution_readout_ms": 1e3 * ident["resolution"][1] if ident else None,
        "rho_readout_offset": rho[0][1] if rho else None,
        "gap": [ana.gap_initial, ana.gap_final, ana.noise_floor], "unexplained": ana.unexplained,
        "cpu_s": time.process_time() - c0}


def verdict(r: dict) -> dict:
    """Per hidden effect: named | ambiguous | missed | named off-tolerance; plus the wrong names."""
    out = {}
    for h in r["hidden"]:
        if h in r["named"]:
            held = ", ".join(r.get("unresolved", []))
            out[h] = ("named" if r["within"].get(h) else "named, out of tolerance") + (
                f" ({held} not resolved: held at nominal)" if held and h == "gyro_bias" else "")
        elif h in r["ambiguous"]:
            out[h] = "ambiguous"
        elif r.get("below_resolution", {}).get(h):
            out[h] = "below resolution"
        else:
            out[h] = "missed"
    return out


def row(r: dict) -> str:
    v = verdict(r)
    vals = r["values"]
    rec = (f"offset {vals['time_offset_ms']:.2f} ms, readout {vals['readout_ms']:.2f} ms, "
           f"τ {vals['tau_ms']:.2f} ms, bias (" + ", ".join(f"{b:.2f}" for b in vals["bias_deg_s"]) + ") °/s")
    rho = "—" if r["rho_readout_offset"] is None else f"{r['rho_readout_offset']:+.3f}"
    sig = "—" if r["sigma_readout_ms"] is None else (f"{r['sigma_readout_ms']:.3f} / "
                                                     f"{r['resolution_readout_ms']:.1f}")
    g = r["gap"]
    return (f"| {r['case']} | {', '.join(r['named']) or 'nothing'} | "
            f"{'; '.join(r['ambiguous_labels']).replace('|', '∣') or '—'} | {', '.join(r['wrong']) or '—'} | "
            f"{'; '.join(f'{k}: {x}' for k, x in v.items())} | {rec} | {rho} | {sig} | "
            f"{g[0]:.4f} → {g[1]:.4f} ({g[2]:.4f}) | {'yes' if r['unexplained'] else 'no'} | "
            f"{r['cpu_s']:.0f} |")


CASE_HEADER = ["| case (log:s:hidden) | named | ambiguous | wrong names | verdict | final values | "
               "ρ(offset, readout) | readout σ / resolution (ms) | gap → final (floor) | unexplained "
               "| CPU s |",
               "|---|---|---|---|---|---|---:|---:|---|---|---:|"]
COLUMNS = (*TIMING, "other", "ambiguous", "below resolution", "nothing")


def confusion(results: list[dict]) -> list[str]:
    """Per log and duration: rows = hidden effect(s), columns = what the search said about each hidden
    effect (its own column when named, `ambiguous`, `nothing`) and every wrong name in its column."""
    lines = []
    for log in LOGS:
        for s in SECONDS:
            rs = [r for r in results if r["case"].startswith(f"{log}:{s:g}:")]
            if not rs:
                continue
            lines += ["", f"**{log}, {s:g} s** (truth × named; a pair's row counts each of its effects)", "",
                      "| truth | " + " | ".join(COLUMNS) + " |", "|---|" + "---:|" * len(COLUMNS)]
            for r in rs:
                cells = dict.fromkeys(COLUMNS, 0)
                for h, what in verdict(r).items():
                    col = what if what in ("ambiguous", "below resolution") else "nothing"
                    cells[h if what.startswith("named") else col] += 1
                for w in r["wrong"]:
                    cells[w if w in TIMING else "other"] += 1
                lines.append(f"| {'+'.join(r['hidden'])} | "
                             + " | ".join(str(cells[c]) for c in COLUMNS) + " |")
    return lines


def totals(results: list[dict]) -> tuple[int, int, int, int, int]:
    """(wrong names, hidden effects named in tolerance, ambiguous, below resolution, missed or out of
    tolerance)."""
    wrong = sum(len(r["wrong"]) for r in results)
    v = [x for r in results for x in verdict(r).values()]
    named = sum(x == "named" or x.startswith("named (") for x in v)
    amb, below = v.count("ambiguous"), v.count("below resolution")
    return wrong, named, amb, below, len(v) - named - amb - below


def write(out: Path, results: list[dict]) -> None:
    wrong, named, amb, below, missed = totals(results)
    n = named + amb + below + missed
    done = {r["case"] for r in results}
    todo = [n for n in case_names() if n not in done]
    body = [SECTION, "",
            f"<!-- summary: motion-only discrepancy on flights from three real logs (0.8 s and 3 s, roll, "
            f"640×480), each timing effect alone and the offset + readout pair | {wrong} wrong names; "
            f"{named} named, {amb} ambiguous, {below} below the flight's resolution, {missed} missed of {n} "
            f"hidden effects "
            f"({len(results)} of {len(case_names())} cases) | 0 wrong names -->", "",
            __doc__.split("\n\n")[1].replace("\n", " "), "",
            f"Totals: **{wrong} wrong names**; of {n} hidden effects {named} named within tolerance, {amb} "
            f"reported ambiguous, {below} below the resolution the report states, {missed} missed or out "
            "of tolerance.", ""]
    body += CASE_HEADER + [row(r) for r in results]
    body += confusion(results)
    body += ["", "Command (each case also alone: `--cases bf42:0.8:rolling_readout`):",
             "`nice .venv/bin/python -m benchmarks.bench_discrepancy_confusion --out "
             "benchmarks/results/discrepancy_heldout.md`"]
    if todo:
        body += ["", f"Not measured yet ({len(todo)} cases; run them with the command above, `nice`, "
                 "and `--cases` to split them over processes): "
                 + ", ".join(f"`{n}`" for n in todo) + "."]
    text = out.read_text() if out.exists() else "# Held-out motion-only discrepancy\n"
    head = text.split(SECTION)[0].rstrip("\n")
    out.write_text(head + "\n\n" + "\n".join(body) + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=",".join(case_names()), help="comma-separated LOG:SECONDS:EFFECT")
    ap.add_argument("--out", default=None, help="write the table into this results file's confusion section")
    ap.add_argument("--list", action="store_true", help="print the case names and exit")
    args = ap.parse_args(argv)
    if args.list:
        print("\n".join(case_names()))
        return 0
    data = shared_data_dir()
    if data is None or not (data / "logs").is_dir():
        raise SystemExit("the real logs (../shared/data/logs, or $THERMOD_SHARED_DATA) are needed")
    names = [n for n in args.cases.split(",") if n]
    unknown = [n for n in names if n not in case_names()]
    if unknown:
        raise SystemExit(f"--cases: unknown {unknown}; `--list` names them")
    cache = RESULTS

    def load() -> list[dict]:
        if not cache.exists():
            return []
        return [json.loads(x) for x in cache.read_text().splitlines() if x.strip()]

    print("\n".join(CASE_HEADER), flush=True)
    for name in names:
        r = next((x for x in load() if x["case"] == name), None)
        if r is None:
            r = run_case(name, data)
            with cache.open("a") as f:
                f.write(json.dumps(r) + "\n")
        print(row(r), flush=True)
    order = {n: i for i, n in enumerate(case_names())}
    results = sorted(load(), key=lambda x: order.get(x["case"], 1 << 30))
    print("\n".join(confusion(results)))
    wrong, named, amb, below, missed = totals(results)
    print(f"\n{wrong} wrong names; {named} named, {amb} ambiguous, {below} below resolution, {missed} missed")
    if args.out:
        write(Path(args.out), results)
    return 1 if wrong else 0


if __name__ == "__main__":
    sys.exit(main())

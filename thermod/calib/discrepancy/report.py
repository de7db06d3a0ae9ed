"""Outputs: report.json, report.md, model.toml (the fitted [calibration] in a full configuration)
and the figures (residual maps per step, gap per step, the diagnostic panel behind each effect)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from thermod.calib.discrepancy.effects import format_params, format_resolution
from thermod.errors import ConfigError
from thermod.io.json_safe import jsonable
from thermod.physics.calibration import Calibration

if TYPE_CHECKING:
    from thermod.calib.discrepancy.analysis import Analysis


def calibration_toml(calib: Calibration) -> str:
    """`[calibration]` table with the recording attribute names (ready for `thermod run --config`)."""
    lines = ["# written by `thermod discrepancy`: the model the recordings support", "[calibration]"]
    for k, v in calib.as_dict().items():
        if k in ("width", "height"):
            lines.append(f"{k} = {int(v)}")
        elif isinstance(v, list) and v and isinstance(v[0], list):
            rows = ("[" + ", ".join(repr(float(x)) for x in row) + "]" for row in v)
            lines.append(f"{k} = [" + ", ".join(rows)
                         + "]")
        elif isinstance(v, list):
            lines.append(f"{k} = [" + ", ".join(repr(float(x)) for x in v) + "]")
        else:
            lines.append(f"{k} = {float(v)!r}")
    return "\n".join(lines) + "\n"


def replace_calibration_table(text: str, calib: Calibration) -> str:
    """`text` (a thermod TOML) with its [calibration] table replaced by `calib` (appended if absent)."""
    table = calibration_toml(calib).split("\n", 1)[1]          # drop the header comment
    lines = text.splitlines(keepends=True)
    start = next((i for i, ln in enumerate(lines) if ln.split("#")[0].strip() == "[calibration]"), None)
    if start is None:
        return text.rstrip("\n") + "\n\n" + table
    end = next((i for i in range(start + 1, len(lines)) if lines[i].lstrip().startswith("[")), len(lines))
    return "".join(lines[:start]) + table + ("\n" if end < len(lines) else "") + "".join(lines[end:])


def _figures(ana: Analysis, out: Path) -> list[str]:
    import matplotlib
    matplotlib.use("Agg")

    files = [_residual_maps_figure(ana, out / "residual_maps.png"),
             _gap_figure(ana, out / "gap_per_step.png")]
    for i, ((effect, dg), step) in enumerate(zip(ana.diags, ana.steps, strict=True)):
        path = out / f"diagnostics_step{i + 1}_{effect}.png"
        _diag_figure(dg, step["diagnostic"], f"before step {i + 1}: {effect}", path)
        files.append(path.name)
    return files


def _residual_maps_figure(ana: Analysis, path: Path) -> str:
    """RMS residual over the motion frames of the first recording, before and after each step."""
    import matplotlib.pyplot as plt

    n = len(ana.snapshots)
    vmax = max(float(np.percentile(s[1], 99)) for s in ana.snapshots) or 1.0
    fig, axes = plt.subplots(1, n, figsize=(3.6 * n, 3.2), squeeze=False)
    for ax, (label, img, gap) in zip(axes[0], ana.snapshots, strict=True):
        im = ax.imshow(img, cmap="magma", vmin=0, vmax=vmax)
        ax.set_title(f"{'after ' + label if label != 'nominal' else 'nominal'}\ngap {gap:.4f}", fontsize=9)
        ax.axis("off")
    fig.colorbar(im, ax=axes[0].tolist(), shrink=0.8, label="residual RMS (counts)")
    fig.suptitle("RMS residual (measured − predicted) per pixel over the motion frames of the first "
                 "recording, working resolution", fontsize=9)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path.name


def _gap_figure(ana: Analysis, path: Path) -> str:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.2))
    labels = [g[0] for g in ana.gaps]
    ax.plot(range(len(labels)), [g[1] for g in ana.gaps], "o-", label="gap")
    ax.plot(range(len(labels)), [g[2] for g in ana.gaps], "k--", label="noise floor")
    ax.set_xticks(range(len(labels)), labels, rotation=20, fontsize=8)
    ax.set_ylabel("gap (residual / motion signal)")
    ax.set_xlabel("model after each step")
    ax.set_title("gap per step and the noise floor (what a perfect model leaves)", fontsize=9)
    ax.set_ylim(bottom=0)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path.name


def _diag_figure(dg: dict, highlight: str, title: str, path: Path) -> None:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(4, 3, figsize=(12, 12.5))
    ax = axes.ravel()
    panels = {}
    ax[0].plot(dg["row_gap"], lw=1)
    ax[0].set(xlabel="image row (working res.)", ylabel="gap", title="gap per image row (rolling readout)")
    panels["row"] = ax[0]
    ax[1].plot(dg["t"], dg["frame_gap"], "o", ms=3)      # points: several recordings share the axis
    ax[1].set(xlabel="time since motion onset (s)", ylabel="gap", title="gap per frame vs time (bias drift)")
    panels["time"] = ax[1]
    ax[2].plot(dg["speed_deg_s"], dg["frame_gap"], "o", ms=3)
    ax[2].set(xlabel="|ω| (°/s)", ylabel="gap", title="gap per frame vs angular rate (scale, misalignment)")
    panels["rate"] = ax[2]
    ax[3].plot(dg["accel_deg_s2"], dg["frame_gap"], "o", ms=3)
    ax[3].set(xlabel="|dω/dt| (°/s²)", ylabel="gap", title="gap per frame vs angular acceleration (τ)")
    panels["accel"] = ax[3]
    ax[4].semilogy(dg["spectrum_freq"], dg["spectrum"], "o-", label="residual")
    ax[4].axhline(max(dg["spectrum_noise"], 1e-12), color="k", ls="--", lw=0.8, label="white noise")
    ax[4].set(xlabel="spatial frequency (cycles/px)", ylabel="power",
              title="radial power spectrum of the residual (PSF)")
    ax[4].legend(fontsize=8)
    panels["spectrum"] = ax[4]
    ax[5].plot(dg["t"], np.asarray(dg["lag_s"]) * 1e3, "o", ms=3)
    ax[5].axhline(0, color="k", lw=0.8)
    ax[5].set(xlabel="time since motion onset (s)", ylabel="lag (ms)",
              title=f"kernel-centroid lag per frame (median {_ms(dg['lag_median_s'])})")
    panels["lag"] = ax[5]
    panels.update(_gyro_panels(ax[6:9], dg))
    _detector_panels(dg, ax[9], ax[10], panels)
    ax[11].axis("off")
    ax[11].text(0, 0.5, "Each panel: the residual of the model before this step,\nagainst what one "
                "candidate effect would change\n(the effect is named in brackets).", fontsize=9)
    for k, a in panels.items():
        if k == highlight:
            for s in a.spines.values():
                s.set_color("red")
                s.set_linewidth(2.5)
    fig.suptitle(title + f"  (red: the diagnostic for {highlight})")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def _ms(seconds: float) -> str:
    return f"{seconds * 1e3:.2f} ms" if np.isfinite(seconds) else "n/a"


def _detector_panels(dg: dict, ax_resp, ax_ffc, panels: dict) -> None:
    """The detector-side panels: residual vs the blur's mixing variance (a curved response), and the
    per-frame residual energy and frame-to-frame change against time (flat-field corrections)."""
    if "mix_var" in dg:
        ax_resp.plot(dg["mix_var"], dg["mix_residual"], "o-", ms=3, label="binned residual")
        xx = np.array([0.0, np.nanmax(dg["mix_var"]) if np.any(np.isfinite(dg["mix_var"])) else 1.0])
        ax_resp.plot(xx, dg["mix_slope"] * xx, "k--", lw=0.8, label=f"slope γ = {dg['mix_slope']:.3g}/count")
        ax_resp.axhline(0, color="k", lw=0.5)
        ax_resp.legend(fontsize=8)
    ax_resp.set(xlabel="variance the blur mixes, P(r²) − P(r)² (counts²)", ylabel="mean residual (counts)",
                title="mean residual vs blur mixing (detector response)")
    panels["response"] = ax_resp
    if "frame_energy" in dg:
        t = dg["ffc_t"]
        ax_ffc.semilogy(t, np.maximum(dg["frame_energy"], 1e-3), "o-", ms=3, label="residual energy")
        ax_ffc.semilogy(t, np.maximum(dg["change_measured"], 1e-3), "s", ms=3, mfc="none",
                        label="measured change")
        ax_ffc.semilogy(t, np.maximum(dg["change_predicted"], 1e-3), "+", ms=4, label="predicted change")
        fz = np.asarray(dg["frozen"], bool)
        if fz.any():
            ax_ffc.semilogy(t[fz], np.maximum(dg["frame_energy"][fz], 1e-3), "rx", ms=8, label="frozen")
        for a, b in dg["ffc_events"]:
            ax_ffc.axvspan(a, b, color="0.85")
            ax_ffc.axvline(b, color="r", lw=1)
        ax_ffc.legend(fontsize=7)
    ax_ffc.set(xlabel="time since motion onset (s)", ylabel="per frame / noise variance",
               title="residual and change vs time (FFC)")
    panels["ffc"] = ax_ffc


def _gyro_panels(ax, dg: dict) -> dict:
    """The gyro-side panels (see `diagnostics.gyro_panels`): clock drift, low-pass, saturation."""
    import matplotlib
    import matplotlib.ticker
    t, lag = np.asarray(dg["t"]), np.asarray(dg["lag_s"]) * 1e3
    ax[0].plot(t, lag, "o", ms=3)
    ok = np.isfinite(lag)
    if ok.sum() >= 3 and np.isfinite(dg["lag_slope_ppm"]):
        p = np.polyfit(t[ok], lag[ok], 1)
        ax[0].plot(t, np.polyval(p, t), "r-", lw=1)
    ax[0].set(xlabel="time since motion onset (s)", ylabel="lag (ms)",
              title="lag trend " + (f"{dg['lag_slope_ppm']:.0f} ppm" if np.isfinite(dg["lag_slope_ppm"])
                                    else "n/a (too few moving frames)") + " (clock drift)")
    ax[1].semilogx(np.maximum(dg["motion_freq_hz"], 0.1), lag, "o", ms=3)
    ax[1].axhline(0, color="k", lw=0.8)
    ax[1].xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())     # the minor labels overlap
    ax[1].set(xlabel="motion frequency |dω/dt|/(2π|ω|) (Hz)", ylabel="lag (ms)",
              title="lag vs motion frequency (gyro low-pass)")
    top = np.degrees(np.asarray(dg["gyro_abs_max"]))
    ax[2].hist(top, bins=60, log=True)
    if dg["clip_level"] > 0:
        ax[2].axvline(np.degrees(dg["clip_level"]), color="r", lw=1)
    n_clip = int(np.sum(dg["frame_clipped"]))
    ax[2].set(xlabel="max raw |ω| over axes (°/s)", ylabel="samples",
              title=f"gyro range: pile-up at {np.degrees(dg['clip_level']):.4g} °/s, {n_clip} frames hit"
              if dg["clip_level"] > 0 else "gyro range: no pile-up (saturation)")
    return {"lag_trend": ax[0], "lag_freq": ax[1], "clip": ax[2]}


def write_report(ana: Analysis, out: str | Path, inputs: list[str], config_text: str) -> dict:
    """DIR/report.json, report.md, model.toml and the figures; returns the JSON report.

    model.toml is `config_text` (a full thermod configuration: the command passes the --config file, else
    the packaged default) with its [calibration] table replaced, so it is ready for `thermod run
    --config` as well as `thermod deblur --config` (which reads only the table).
    """
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"--out {out}: cannot create the output directory ({e.strerror})") from None
    rep = jsonable(ana.report())
    rep["inputs"] = [str(p) for p in inputs]
    try:
        (out / "report.json").write_text(json.dumps(rep, indent=2, allow_nan=False) + "\n")
        (out / "model.toml").write_text(_ambiguous_header(ana)
                                        + replace_calibration_table(config_text, ana.calibration()))
        figs = _figures(ana, out)
        (out / "report.md").write_text(_markdown(ana, rep["inputs"], figs))
    except OSError as e:
        raise ConfigError(f"--out {out}: cannot write the report ({e.filename}: {e.strerror})") from None
    return rep


def _ambiguous_header(ana: Analysis) -> str:
    """Comment lines for model.toml: which fields stay at the values under test because the flight could
    not tell their effects apart."""
    return "".join(f"# {a['label']}: their fields keep the values under test; to separate them record "
                   f"{a['separating_motion']}\n" for a in ana.ambiguous) + "".join(
        f"# {u['effect']}: {u['param']} not resolved by this motion (joint fit {u['joint_value']:.4g}, "
        f"resolution ±{u['resolution']:.2g}): it keeps the value under test\n"
        for u in ana.identifiability.get("unresolved", []))


def _identifiability_md(ana: Analysis) -> list[str]:
    """The identifiability section: the rule, each timing parameter's σ and resolution, the pairs'
    correlations, each effect's test, and any ambiguous entry with its evidence."""
    idf = ana.identifiability
    if not idf:
        return []
    md = ["", "## Identifiability of the timing effects", "", f"Rule: {idf['rule']}.", "",
          "| parameter | fitted (kept) | nominal | σ (noise) | resolution (min_gain) |",
          "|---|---|---|---|---|"]
    for name, v, n, s, r in zip(idf["params"], idf["values"], idf["nominal"], idf["sigma"], idf["resolution"],
                                strict=True):
        md.append(f"| {name} | {v:.4g} | {n:.4g} | {s:.2g} | {r:.2g} |")
    md += ["", "Correlations of the joint fit's estimates:", "",
           "| | " + " | ".join(idf["params"]) + " |", "|---|" + "---:|" * len(idf["params"])]
    for name, row in zip(idf["params"], idf["correlation"], strict=True):
        md.append(f"| {name} | " + " | ".join(f"{v:+.3f}" for v in row) + " |")
    md += ["", "| effect held at nominal (others refitted) | gap without | gap joint | ΔBIC | "
           "rise / min_gain | verdict |", "|---|---|---|---|---|---|"]
    for e, t in idf["tests"].items():
        md.append(f"| {e} | {t['gap_without']:.4f} | {t['gap_joint']:.4f} | {t['delta_bic']:.1f} | "
                  f"{t['delta_ssr_share']:.2f} | {'identified' if t['identified'] else 'not identified'} |")
    for u in idf.get("unresolved", []):
        md += ["", f"**{u['effect']}: {u['param']} not resolved** — its joint value {u['joint_value']:.4g} "
               f"lies within its resolution ±{u['resolution']:.2g} (σ {u['sigma']:.2g}) of nominal; it is "
               "held at nominal and the effect is named on its other axes."]
    for a in ana.ambiguous:
        md += ["", f"**{a['label']}** — not named, and model.toml keeps their values under test.", ""]
        md += [f"- {x}" for x in a["evidence"]]
        md += ["- σ: " + ", ".join(f"{k} {v:.2g}" for k, v in a["sigma"].items())
               + "; resolution: " + ", ".join(f"{k} {v:.2g}" for k, v in a["resolution"].items()),
               "- joint fit (one of the solutions the data allow): "
               + ", ".join(f"{k} {v:.4g}" for k, v in a["joint_values"].items()),
               f"- motion that would separate them: {a['separating_motion']}"]
    return md


def _detector_notes(ana: Analysis) -> list[str]:
    """Notes for the detector-side effects: what model.toml does not carry."""
    out = []
    r = ana.model.response
    if r is not None and r.gamma != 0.0:
        out += [f"- Detector response: linearise the raw counts y before deblurring with x = c0 + u + γu², "
                f"u = y − c0, c0 = {r.level:.1f} counts, γ = {r.gamma:.4g} per count. It is not in "
                "model.toml's [calibration]: `thermod run`/`deblur` deconvolve the counts as they come."]
    for e in ana.model.ffc:
        out += [f"- Flat-field correction in {e.recording}: frames frozen from t = {e.t_start:.4f} s to "
                f"{e.t_end:.4f} s (camera clock), then an offset step of {e.step_counts:.2f} counts; the "
                "daemon passes such frames through (reason `ffc`) when the camera flags them."]
    return out


def _markdown(ana: Analysis, inputs: list[str], figs: list[str]) -> str:
    md = ["# thermod discrepancy report", "", f"Inputs: {', '.join(inputs)}", "",
          f"- gap: {ana.gap_initial:.4f} (nominal) → {ana.gap_final:.4f} (final); "
          f"noise floor {ana.noise_floor:.4f}",
          "- gap = ‖measured − predicted‖ / ‖measured − static reference‖ over valid pixels of the "
          "motion frames",
          f"- unexplained structure left: **{'yes' if ana.unexplained else 'no'}**",
          *([f"- **search capped**: {ana.capped}; the steps below are those it completed"]
            if ana.capped else []),
          *[f"- **{a['label']}**: the flight cannot tell these apart (see Identifiability); none is named"
            for a in ana.ambiguous],
          *[f"- **{u['effect']} {u['param']}**: not resolved by this flight (see Identifiability); it keeps "
            "the value under test" for u in ana.identifiability.get("unresolved", [])],
          *([f"- resolution of this flight: a timing effect smaller than {format_resolution(ana.resolution)} "
             "(its change from the model; the others refitted) cannot be named from this motion"]
            if ana.resolution else []),
          f"- reference: **{ana.reference}** ("
          + ("mean of the static lead-in" if ana.reference == "static" else
             "no static lead-in: a scene canvas estimated by least squares from the moving frames")
          + f"); noise from {ana.noise_source}", "",
          "| step | effect | parameters | gap before | gap after | ΔBIC | excess explained |",
          "|---|---|---|---|---|---|---|"]
    for i, s in enumerate(ana.steps, 1):
        md.append(f"| {i} | {s['effect']} | {format_params(s['params'])} | {s['gap_before']:.4f} | "
                  f"{s['gap_after']:.4f} | {s['delta_bic']:.0f} | {100 * s['excess_explained']:.0f} % |")
    if not ana.steps:
        md.append("| – | nothing added | | | | | |")
    for p in ana.pruned:
        md.append(f"| – | {p['effect']} (dropped) | {format_params(p['params'])} | | | | "
                  f"redundant: gap {p['gap_with']:.4f} with it, {p['gap_without']:.4f} without |")
    static = ana.reference != "motion"
    md += ["", "Notes:", ""]
    md += (["- The reference is the mean of the static frames, so it already carries the optics' PSF and the "
            "fixed-pattern noise: a PSF shared by static and moving frames leaves no gap and cannot be "
            "estimated here; `optical_psf` fits only blur that the moving frames have *in addition*."]
           if static else
           ["- There is no static reference: a blur every frame shares (the optics' PSF) is part of the "
            "estimated scene, so `optical_psf` cannot be estimated from this recording; neither can a "
            "uniform offset or gain common to all frames. A detector response curve is mostly taken up "
            "by the scene too (only where the motion blur mixes levels does it leave a trace): record a "
            "static lead-in to measure it."])
    md += ["- FPN is estimated as the high-passed temporal mean of the motion residual (it stays on the "
           "sensor while the scene moves) and added back to every prediction."]
    md += (["- A gyro bias hypothesis uses the static segment's mean raw rate as a prior (the camera is "
            "still there), refined by the images."] if static else
           ["- No static segment: the gyro bias is fitted from the images alone (no prior)."])
    md += _detector_notes(ana)
    md += _identifiability_md(ana)
    if ana.unobservable:
        md += ["", "Not observable with this motion (left at their previous values):"]
        md += [f"- {k}: {', '.join(v)}" for k, v in ana.unobservable.items()]
    md += ["", "## Candidates tried", "", "| step | effect | gap | ΔBIC | excess explained | parameters |",
           "|---|---|---|---|---|---|"]
    for c in ana.candidates_tried:
        md.append(f"| {c['step']} | {c['effect']} | {c['gap']:.4f} | {c['delta_bic']:.0f} | "
                  f"{100 * c['excess_explained']:.0f} % | {format_params(c['params'])} |")
    md += ["", "## Figures", ""] + [f"![{f}]({f})" for f in figs]
    md += ["", "The updated model is in `model.toml` (`thermod run --config model.toml`, `thermod deblur`).",
           ""]
    return "\n".join(md)

"""`thermod discrepancy`'s outputs are valid and quiet (issue 25, goal 4): report.json is strict JSON,
no numpy warning reaches the terminal, every figure panel says what it shows; and the noise floor of a
noiseless recording is not 0 (goal 1). Small recordings (128×96, analysed at 64×48), so this is cheap."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from thermod.calib import discrepancy as D
from thermod.calib.discrepancy.data import quantisation_variance
from thermod.cli import sim as sim_cli
from thermod.io import recording
from thermod.io.json_safe import jsonable
from thermod.runtime import config
from thermod.sim.flight_recordings import flight_recording, nominal_calibration

pytestmark = pytest.mark.heavy(2)      # CPU minutes on one core (about 1.5 on a bare clone)


def _strict(text: str):
    def reject(name):
        raise ValueError(f"non-standard JSON constant {name}")
    return json.loads(text, parse_constant=reject)


def test_jsonable_turns_non_finite_numbers_into_null():
    v = jsonable({"a": np.float32("nan"), "b": [1.0, math.inf, np.float64(-np.inf)], "c": np.int64(3),
                  "d": np.bool_(True)})
    assert v == {"a": None, "b": [1.0, None, None], "c": 3, "d": True}
    json.dumps(v, allow_nan=False)
    assert D.format_params({"x": None, "y": [None, 1.5]}) == "x=n/a y=[n/a, 1.5]"


@pytest.fixture(scope="module")
def flight_file(tmp_path_factory) -> Path:
    fr = flight_recording({"time_offset": 0.006}, seconds=0.3, size=(128, 96), seed=2)
    path = tmp_path_factory.mktemp("flight") / "flight.h5"
    recording.write(path, fr.rec)
    return path


@pytest.mark.slow
def test_cli_output_is_strict_json_with_no_numpy_warning(flight_file, tmp_path):
    # every RuntimeWarning (numpy's divide, invalid value, mean of an empty slice…) is an error here
    out = tmp_path / "report"
    proc = subprocess.run([sys.executable, "-W", "error::RuntimeWarning", "-m", "thermod.cli", "discrepancy",
                           str(flight_file), "--out", str(out), "--work-width", "64",
                           "--candidates", "time_offset,rolling_readout"],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "Warning" not in proc.stderr, proc.stderr[-2000:]
    rep = _strict((out / "report.json").read_text())
    assert rep["reference"] == "motion" and rep["noise_floor"] > 0
    # which kernel explains the smear: one entry per recording, said on stdout too
    sm = _strict((out / "smear.json").read_text())
    assert [e["recording"] for e in sm] == [str(flight_file)]
    assert set(sm[0]["models"]) == {"none", "box", "exponential"}
    assert "which kernel explains the smear" in proc.stdout
    if sm[0]["frames"]:
        assert (out / "smear_0.png").stat().st_size > 0


@pytest.mark.slow
def test_a_non_finite_value_in_the_analysis_is_written_as_null(flight_file, tmp_path):
    rec = recording.read(flight_file)
    d = D.prepare(rec, rec.calibration, name="flight.h5", work_width=64)
    ana = D.analyse([d], D.Model(rec.calibration), candidates=(), min_pixels=500)
    ana.candidates_tried.append({"step": 1, "effect": "time_offset", "params": {"time_offset_s": math.nan},
                                 "gap": math.inf, "delta_bic": -math.inf, "excess_explained": math.nan,
                                 "unobservable": []})
    rep = D.write_report(ana, tmp_path, ["flight.h5"], config.default_path().read_text())
    text = (tmp_path / "report.json").read_text()
    back = _strict(text)
    assert back == rep
    assert back["candidates"][-1]["gap"] is None and back["candidates"][-1]["params"]["time_offset_s"] is None


@pytest.mark.slow
def test_every_figure_panel_has_a_title_and_labelled_axes(flight_file, tmp_path, monkeypatch):
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    seen = []
    save = Figure.savefig

    def keep(fig, path, *a, **kw):
        seen.append((Path(path).name, fig))
        return save(fig, path, *a, **kw)
    monkeypatch.setattr(Figure, "savefig", keep)
    rec = recording.read(flight_file)
    d = D.prepare(rec, rec.calibration, name="flight.h5", work_width=64)
    ana = D.analyse([d], D.Model(rec.calibration), candidates=("time_offset",), min_pixels=500)
    assert ana.named == ["time_offset"]
    D.write_report(ana, tmp_path, ["flight.h5"], config.default_path().read_text())
    names = [n for n, _ in seen]
    assert names == ["residual_maps.png", "gap_per_step.png", "diagnostics_step1_time_offset.png"]
    for name, fig in seen:
        assert fig.get_suptitle() or name == "gap_per_step.png", name
        for ax in fig.axes:
            if not ax.axison and not ax.images:     # the text panel, or a colour bar
                continue
            if ax.get_label() == "<colorbar>":
                assert ax.get_ylabel(), name
                continue
            assert ax.get_title(), (name, ax)
            if not ax.images:                       # plots: both axes say what they are
                assert ax.get_xlabel() and ax.get_ylabel(), (name, ax.get_title())


def test_noiseless_static_recording_has_a_noise_floor_above_zero():
    # identical static frames (NETD 0): the floor is the counts' quantisation, never 0
    from thermod.sim.synth import simulate

    nominal = nominal_calibration((128, 96))
    rec = simulate("texture", "static:0.12+pan:40", 0.3, nominal, {"netd": 0.0}, seed=1)
    d = D.prepare(rec, nominal, name="noiseless.h5", work_width=64)
    assert d.reference == "static"
    assert d.noise_var == pytest.approx(quantisation_variance(d.fm.scale))
    problem = D.Problem([d])
    problem.refresh(D.Model(nominal))
    assert problem.noise_floor() > 0


def test_sim_defaults_to_a_realistic_netd(tmp_path):
    out = tmp_path / "rec.h5"
    assert sim_cli.DEFAULT_NETD_K == pytest.approx(0.05)
    from thermod.cli import main

    assert main(["sim", "-o", str(out), "--motion", "static", "--seconds", "0.1", "--width", "64",
                 "--height", "48", "--no-progress"]) == 0
    rec = recording.read(out)
    f = rec.frames.astype(np.float64)
    temporal = float(np.mean(np.var(f, axis=0, ddof=1)))
    assert temporal > 1.0, temporal          # 50 mK of noise, not identical frames
    assert main(["sim", "-o", str(out), "--motion", "static", "--seconds", "0.1", "--width", "64",
                 "--height", "48", "--no-progress", "--effect", "netd=0"]) == 0
    f0 = recording.read(out).frames.astype(np.float64)
    assert float(np.mean(np.var(f0, axis=0, ddof=1))) < 0.01 * temporal

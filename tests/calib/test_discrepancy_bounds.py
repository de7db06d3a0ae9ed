"""`thermod discrepancy` on recordings whose calibration or gyro fields are extreme but valid-looking:
every size and run time the file drives is bounded (a coarser working image, fewer frames, each
logged) or the value is refused in one line naming the file and the field (exit 2). Each case runs
the real command line in a subprocess with a deadline and, where memory is the point, an
address-space limit; recordings come from `thermod sim`, altered with h5py."""

from __future__ import annotations

import resource
import subprocess
import sys

import h5py
import numpy as np
import pytest

from tests.support.h5edit import edited_copy
from thermod.calib.discrepancy import data as D
from thermod.calib.smear import TAU_SCAN
from thermod.physics.calibration import MAX_TAU_S

DEADLINE_S = 120          # far above what a case needs: a hang, not a slow machine, trips it
AS_LIMIT = 3 * 2**30


def _limit_memory():
    resource.setrlimit(resource.RLIMIT_AS, (AS_LIMIT, AS_LIMIT))


def _thermod(*args, memory: bool = False, code: str | None = None):
    """The command line in a subprocess (`code`: Python run before `main`, e.g. to lower a budget)."""
    pre = (code or "") + "\nimport sys\nfrom thermod.cli import main\nsys.exit(main(sys.argv[1:]))"
    return subprocess.run([sys.executable, "-c", pre, *map(str, args)], capture_output=True, text=True,
                          timeout=DEADLINE_S, preexec_fn=_limit_memory if memory else None)


@pytest.fixture(scope="module")
def sim_recording(tmp_path_factory):
    """160×120, 0.2 s static then 0.3 s of shake, as `thermod sim` writes it."""
    p = tmp_path_factory.mktemp("bounds") / "sim.h5"
    r = _thermod("sim", "-o", p, "--motion", "static:0.2+shake:2", "--seconds", "0.5", "--width", "160",
                 "--height", "120", "--ifov-deg", "0.1564", "--no-truth", "--no-progress")
    assert r.returncode == 0, r.stderr
    return p


def _attrs(group: str, **values):
    def edit(f):
        for k, v in values.items():
            f[group].attrs[k] = v
    return edit


def _run(path, tmp_path, *extra, memory=True, code=None):
    return _thermod("discrepancy", path, "--out", tmp_path / "out", *extra, memory=memory, code=code)


# Quick settings for the runs that must succeed: one cheap candidate, one step (the bounds are in the
# preparation, which every run goes through).
QUICK = ("--candidates", "time_offset", "--max-steps", "1", "--no-fpn")


REFUSED = {
    # name: (edit, what the one-line error names besides the file)
    "offset_-0.9s": (_attrs("gyro", time_offset_s=-0.9), "gyro.attrs['time_offset_s']"),
    "offset_+0.9s": (_attrs("gyro", time_offset_s=0.9), "gyro.attrs['time_offset_s']"),
    "tau_1us": (_attrs("camera", tau_s=1e-6), "camera.attrs['tau_s']"),
    "tau_nan": (_attrs("camera", tau_s=float("nan")), "camera.attrs['tau_s']"),
}


@pytest.mark.parametrize("case", list(REFUSED))
def test_out_of_range_values_are_refused_naming_file_and_field(case, sim_recording, tmp_path):
    edit, field = REFUSED[case]
    path = edited_copy(sim_recording, tmp_path / f"{case}.h5", edit)
    if case == "tau_1us":         # τ-bound steps over 1 s of motion: beyond any working resolution
        with h5py.File(path, "r+") as f:
            _stretch_motion(f)
    r = _run(path, tmp_path)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, lines
    assert f"{case}.h5" in lines[0] and field in lines[0] and "expected" in lines[0], lines


def _stretch_motion(f):
    """Frames and gyro repeated four times end to end (the same rates, 2 s in all)."""
    fr, t, gt, gr = f["camera/frames"][()], f["camera/t"][()], f["gyro/t"][()], f["gyro/rate"][()]
    span = len(t) * (t[1] - t[0])
    T = np.concatenate([t + k * span for k in range(4)])
    GT = np.concatenate([gt + k * span for k in range(4)])
    GR = np.concatenate([gr] * 4)
    keep = GT > np.maximum.accumulate(np.r_[-np.inf, GT[:-1]])
    for k in ("camera/frames", "camera/t", "gyro/t", "gyro/rate"):
        del f[k]
    f["camera/frames"] = np.concatenate([fr] * 4)
    f["camera/t"], f["gyro/t"], f["gyro/rate"] = T, GT[keep], GR[keep].astype(np.float32)


def test_large_frames_are_binned_as_they_are_read(sim_recording, tmp_path):
    # 1024×1024 frames under a lowered frame budget stand for 4096×4096 ones: read one at a time and
    # binned to the working resolution, never held at full resolution.
    def upscale(f):
        import cv2

        fr = f["camera/frames"][()]
        del f["camera/frames"]
        f["camera/frames"] = np.stack([cv2.resize(x, (1024, 1024), interpolation=cv2.INTER_NEAREST)
                                       for x in fr])
        a, s = f["camera"].attrs, 1024 / fr.shape[2]
        a["width"], a["height"], a["fx"], a["fy"] = 1024, 1024, a["fx"] * s, a["fx"] * s
        a["cx"] = a["cy"] = 511.5
    path = edited_copy(sim_recording, tmp_path / "big.h5", upscale)
    r = _run(path, tmp_path, *QUICK, code="import thermod.cli.discrepancy as m; m.MAX_FRAMES_MB = 8")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "big.h5: 25 frames of 1024×1024" in r.stderr and "binning them to 128×128" in r.stderr, r.stderr


def test_tau_near_its_upper_end_scans_inside_the_range(sim_recording, tmp_path):
    # τ = 0.6 s: the smear scan (×2^¼ steps up to 2×) and the time-constant fit would step past 1 s.
    assert 0.6 * TAU_SCAN[-1] > MAX_TAU_S
    path = edited_copy(sim_recording, tmp_path / "slow.h5", _attrs("camera", tau_s=0.6))
    r = _run(path, tmp_path, "--candidates", "time_constant", "--max-steps", "1", "--no-fpn", memory=False)
    assert r.returncode == 0, r.stderr[-2000:]
    assert (tmp_path / "out" / "smear.json").is_file()


def test_long_recording_is_worked_on_its_first_motion_frames():
    # the view budget, then the frame window: a long motion at the smallest working image keeps the
    # leading frames that fit (in process: the grid is sized before anything is allocated)
    from thermod.physics.calibration import Calibration

    calib = Calibration(width=64, height=48, fx=80.0, fy=80.0, cx=31.5, cy=23.5)
    t = 100.0 + np.arange(0, 20.0, 0.02)
    gt = np.arange(99.9, 120.0, 0.001)
    rate = np.zeros((len(gt), 3))
    rate[gt > 100.3, 1] = 0.5 * np.sin(2 * np.pi * 1.5 * gt[gt > 100.3])
    frames = np.full((len(t), 48, 64), 1000, np.uint16)
    from thermod.io.recording import Recording

    rec = Recording(frames, t, gt, rate.astype(np.float32), calib)
    d = D.prepare(rec, calib, name="long.h5", work_views_mb=4.0)
    assert 2 <= len(d.frame_t) < len(t) - 15
    assert len(d.fm.t_views) * d.fm.h * d.fm.w * 8 / 1e6 <= 4.0


# The search's work cap, lowered so that it is reached at once on these small recordings (the default is
# far above what they need: see `thermod.cli.discrepancy.MAX_SEARCH_WORK`).
def _cap(work: float) -> str:
    return f"import thermod.cli.discrepancy as m; m.MAX_SEARCH_WORK = {work!r}"


def _assert_capped(r, out):
    """A completed report (exit 0) whose search says, in its output, log and report, that it stopped early."""
    import json

    assert r.returncode == 0, r.stderr[-2000:]
    assert "the search stopped early" in r.stdout and "the search stopped early" in r.stderr, r.stdout
    rep = json.loads((out / "report.json").read_text())
    assert rep["search_capped"].startswith("the search stopped early"), rep["search_capped"]
    assert rep["work_pixel_steps"] >= rep["max_work_pixel_steps"] > 0
    assert "**search capped**" in (out / "report.md").read_text()
    assert (out / "smear.json").is_file() and (out / "model.toml").is_file()
    return rep


def test_search_at_its_work_cap_stops_and_says_so(sim_recording, tmp_path):
    # a 20 ms offset is worth a search; the cap is reached by the nominal model's evaluation already
    path = edited_copy(sim_recording, tmp_path / "late.h5", _attrs("gyro", time_offset_s=0.02))
    r = _run(path, tmp_path, "--candidates", "time_offset,gyro_bias", "--no-fpn", code=_cap(1.0))
    rep = _assert_capped(r, tmp_path / "out")
    assert "before step 1" in rep["search_capped"] and rep["steps"] == []


@pytest.fixture(scope="module")
def motion_step_recording(tmp_path_factory):
    """80×60, 0.4 s of shake with no static lead-in (the motion-only path), and a 1 rad/s step added to
    the gyro's y rate after the first quarter: a motion no effect of the vocabulary explains."""
    p = tmp_path_factory.mktemp("bounds") / "step.h5"
    r = _thermod("sim", "-o", p, "--motion", "shake:2", "--seconds", "0.4", "--width", "80", "--height", "60",
                 "--ifov-deg", "0.3128", "--no-truth", "--no-progress")
    assert r.returncode == 0, r.stderr
    with h5py.File(p, "r+") as f:
        rate, t = f["gyro/rate"][()], f["gyro/t"][()]
        rate[t > t[0] + 0.25 * (t[-1] - t[0]), 1] += 1.0
        f["gyro/rate"][...] = rate
    return p


def test_motion_only_search_at_its_work_cap_completes_its_report(motion_step_recording, tmp_path):
    # the cap falls inside the first step (after the scene canvas and the first fits): that step names
    # nothing, and the report is written with the nominal model
    r = _run(motion_step_recording, tmp_path, "--candidates", "time_offset,time_constant,gyro_bias",
             code=_cap(3e8))
    rep = _assert_capped(r, tmp_path / "out")
    assert "no static lead-in" in r.stdout and rep["reference"] == "motion"
    assert "in step 1" in rep["search_capped"] and rep["steps"] == []


def test_long_focal_length_completes_with_the_smear_scan_inside_what_renders(sim_recording, tmp_path):
    # fx = 1e4 px over 160 px (a 0.92° field of view, a long surveillance lens): the image moves up to
    # ~30× as far as at the nominal focal length, so the smear scan's longer τ would render kernels past
    # the renderer's limit (those frames are left out of the smear comparison, not the whole run)
    path = edited_copy(sim_recording, tmp_path / "tele.h5", _attrs("camera", fx=1e4, fy=1e4))
    r = _run(path, tmp_path, *QUICK, code=_cap(1.0))
    assert r.returncode == 0, r.stderr[-2000:]
    assert (tmp_path / "out" / "smear.json").is_file() and (tmp_path / "out" / "report.md").is_file()

"""Bring your own flight, as a user runs it: `thermod import VIDEO --gyro LOG`, `thermod deblur --video`,
`thermod export --gcsv`, through the real command line (subprocess), on simulated flights written in
every log family thermod reads, and on videos rendered from the real logs in tests/data/flightlogs."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from thermod.io import flightlog, video
from thermod.physics.calibration import Calibration
from thermod.sim.flight_video import MountedMotion, simulate_flight

pytestmark = pytest.mark.heavy(2)      # CPU minutes on one core, subprocesses included (measured 1.5)

REAL_LOGS = Path(__file__).parents[1] / "data" / "flightlogs"
WIDTH, HEIGHT, FPS, TAU = 160, 120, 30.0, 0.008


def thermod(*args, cwd=None) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    env.setdefault("NUMBA_CACHE_DIR", str(Path(__file__).parents[2] / ".numba_cache"))
    return subprocess.run([sys.executable, "-m", "thermod.cli", *map(str, args)], capture_output=True,
                          text=True, env=env, cwd=cwd, timeout=600)


def camera_toml(path: Path, hfov_deg: float, width=WIDTH, height=HEIGHT, fps=FPS) -> Path:
    path.write_text(f"[camera]\nwidth = {width}\nheight = {height}\nhfov_deg = {hfov_deg}\n"
                    f"frame_rate_hz = {fps}\ntau_s = {TAU}\n")
    return path


def simulator_hfov(width=WIDTH, hfov_deg=50.0) -> float:
    """simulate_flight's camera (fx = 1 / IFOV) as a horizontal field of view."""
    fx = 1.0 / math.radians(hfov_deg / width)
    return math.degrees(2 * math.atan(0.5 * width / fx))


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    d = tmp_path_factory.mktemp("flight")
    sim = simulate_flight(d, seconds=4.0, log_seconds=20.0, width=WIDTH, height=HEIGHT, fps=FPS, tau_s=TAU,
                          formats=("gcsv", "betaflight-csv", "ardupilot"), seed=3, mount=17)
    return sim, camera_toml(d / "camera.toml", simulator_hfov())


def check_import(out: Path, log_offset_s: float, camera_from_body: np.ndarray, period_s: float) -> dict:
    with h5py.File(out) as f:
        attrs = dict(f["import"].attrs)
        R = np.array(json.loads(attrs["sync"])["R_cam_gyro"])
        mount = np.array(json.loads(attrs["sync"])["mount"])
    err = abs(float(attrs["log_offset_s"]) - log_offset_s)
    assert err < period_s, f"offset error {err * 1e3:.2f} ms ≥ one frame period"
    np.testing.assert_array_equal(mount, np.rint(camera_from_body).astype(int))
    assert np.allclose(R, camera_from_body, atol=0.05)
    return attrs


@pytest.mark.parametrize("fmt", ["gcsv", "betaflight-csv", "ardupilot"])
def test_import_finds_offset_and_mount_for_each_log_family(flight, fmt, tmp_path):
    sim, cam = flight
    out = tmp_path / "rec.h5"
    r = thermod("import", sim.video_path, "--gyro", sim.log_paths[fmt], "-o", out, "--calibration", cam,
                "--no-refine")
    assert r.returncode == 0, r.stderr
    attrs = check_import(out, sim.log_offset_s, sim.camera_from_body, 1 / FPS)
    assert attrs["log_format"] == fmt and attrs["video_bit_depth"] == 8
    from thermod.io.recording import read
    rec = read(out)
    assert rec.n_frames == len(sim.frame_t_video) and rec.frames.max() <= 255
    assert rec.calibration.time_offset_s == 0.0
    # the gyro is on the video clock: it covers the frames and their kernel windows
    assert rec.gyro_t[0] < rec.t[0] - 5 * TAU and rec.gyro_t[-1] > rec.t[-1]


def test_a_part_of_the_video_imports_on_the_video_clock(flight, tmp_path):
    """--start/--duration (a long flight's part): the frames keep the video's own times, so the log is
    placed as for the whole video."""
    sim, cam = flight
    out = tmp_path / "part.h5"
    r = thermod("import", sim.video_path, "--gyro", sim.log_paths["gcsv"], "-o", out, "--calibration", cam,
                "--no-refine", "--start", "1", "--duration", "2.5")
    assert r.returncode == 0, r.stderr
    check_import(out, sim.log_offset_s, sim.camera_from_body, 1 / FPS)
    from thermod.io.recording import read
    rec = read(out)
    t = np.asarray(sim.frame_t_video)
    keep = (t - t[0] >= 1.0 - 1e-6) & (t - t[0] < 3.5 - 1e-6)
    assert rec.n_frames == keep.sum() and np.allclose(rec.t, t[keep])


@pytest.mark.parametrize("cut", ["armed late", "disarmed early"])
def test_a_log_covering_part_of_the_video_imports_that_part(tmp_path, cut):
    """A flight controller that logs only while armed, a video running from before take-off (or on
    after landing): the part of the video the log covers is found, synced and imported alone."""
    sim = simulate_flight(tmp_path, seconds=10.0, log_seconds=30.0, width=WIDTH, height=HEIGHT, fps=FPS,
                          tau_s=TAU, formats=("gcsv",), seed=4, mount=17)
    cam = camera_toml(tmp_path / "camera.toml", simulator_hfov())
    log = flightlog.read_flight_log(sim.log_paths["gcsv"])
    t = np.asarray(sim.frame_t_video)
    if cut == "armed late":       # the log starts 4 s into the video
        keep = log.t >= t[0] + sim.log_offset_s + 4.0
    else:                         # ... or ends 4 s before the video does
        keep = log.t <= t[-1] + sim.log_offset_s - 4.0
    part = flightlog.write_gcsv(tmp_path / "part.gcsv", log.t[keep], log.rate[keep])
    out = tmp_path / "rec.h5"
    r = thermod("import", sim.video_path, "--gyro", part, "-o", out, "--calibration", cam, "--no-refine")
    assert r.returncode == 0, r.stderr
    assert "the log covers frames" in r.stderr and "the others were left out" in r.stderr
    attrs = check_import(out, sim.log_offset_s, sim.camera_from_body, 1 / FPS)
    i0, i1 = json.loads(attrs["sync"])["frames_covered"]
    from thermod.io.recording import read
    rec = read(out)
    assert np.allclose(rec.t, t[i0:i1]) and 4.5 < rec.t[-1] - rec.t[0] < 6.0
    if cut == "armed late":
        assert i1 == len(t) and 3.9 < t[i0] - t[0] < 4.5
    else:
        assert i0 == 0 and 5.5 < t[i1 - 1] - t[0] < 6.1
    assert rec.gyro_t[0] < rec.t[0] - 5 * TAU and rec.gyro_t[-1] > rec.t[-1]


def test_deblur_video_and_gcsv_export_round_trip(flight, tmp_path):
    import av

    sim, cam = flight
    rec, deb, mp4, gcsv = (tmp_path / n for n in ("rec.h5", "deb.h5", "deb.mp4", "out.gcsv"))
    assert thermod("import", sim.video_path, "--gyro", sim.log_paths["gcsv"], "-o", rec, "--calibration", cam,
                   "--no-refine").returncode == 0
    r = thermod("deblur", rec, "-o", deb, "--video", mp4, "--side-by-side", "--uniform", "--jobs", "1")
    assert r.returncode == 0, r.stderr
    probe = subprocess.run(["ffprobe", "-v", "error", "-count_frames", "-select_streams", "v:0",
                            "-show_entries", "stream=codec_name,width,height,nb_read_frames", "-of", "json",
                            str(mp4)],
                           capture_output=True, text=True, check=True)
    s = json.loads(probe.stdout)["streams"][0]
    assert (s["codec_name"], s["width"], s["height"]) == ("h264", 2 * WIDTH, HEIGHT)
    assert int(s["nb_read_frames"]) == len(sim.frame_t_video)
    with av.open(str(mp4)) as c:
        frames = [f.to_ndarray(format="gray") for f in c.decode(video=0)]
    # the left half is the imported 8-bit frame itself, the right the deblurred one on the same scale
    with h5py.File(rec) as f:
        first = f["camera/frames"][0]
    assert np.median(np.abs(frames[0][:, :WIDTH].astype(int) - first)) <= 2
    right = np.stack([f[:, WIDTH:] for f in frames]).astype(float)
    assert 40 < right.mean() < 215 and right.std() > 20

    r = thermod("export", rec, "--gcsv", gcsv)
    assert r.returncode == 0, r.stderr
    log = flightlog.read_flight_log(gcsv)
    assert log.source_format == "gcsv" and log.orientation == flightlog.GCSV_ORIENTATION_OPENCV_CAMERA
    assert abs(log.rate_hz - sim.gyro_rate_hz) < 1
    # camera-frame rates on the video clock: the truth's body rates through the mount, at t_video + offset
    truth = np.stack([np.interp(log.t + sim.log_offset_s, sim.body_t_log, sim.body_rate[:, a])
                      for a in range(3)], axis=1) @ sim.camera_from_body.T
    inside = (log.t > 0.1) & (log.t < sim.frame_t_video[-1])
    assert np.sqrt(np.mean((log.rate[inside] - truth[inside]) ** 2)) < math.radians(0.5)
    import telemetry_parser
    tp = telemetry_parser.Parser(str(gcsv))
    assert tp.camera == "gyroflow" or "gcsv" in str(tp.camera).lower() or tp.camera
    imu = tp.normalized_imu()
    assert len(imu) == len(log.t)


@pytest.mark.slow
def test_refinement_keeps_the_sync(flight, tmp_path):
    sim, cam = flight
    out, rep = tmp_path / "rec.h5", tmp_path / "report"
    # 2 s of the 4 s flight: the refinement names nothing on either (its search of the whole flight took
    # 141 s of a make test's 16 min, this part 10 s)
    r = thermod("import", sim.video_path, "--gyro", sim.log_paths["ardupilot"], "-o", out,
                "--calibration", cam, "--report", rep, "--refine", "--duration", "2")
    assert r.returncode == 0, r.stderr
    attrs = check_import(out, sim.log_offset_s, sim.camera_from_body, 1 / FPS)
    ref = json.loads(attrs["refinement"])
    # issue 34: the refinement carries the identifiability check's σ and says what it could not tell
    # apart; an ambiguous effect is reported, not written
    assert len(ref["ambiguous"]) == len(ref["identifiability"]) == len(ref["named"]) == 1
    ident = ref["identifiability"][0]
    if ident:
        assert len(ident["sigma"]) == len(ident["params"]) and all(s >= 0 for s in ident["sigma"])
    unsure = {e for a in ref["ambiguous"][0] for e in a["effects"]}
    assert not unsure & set(ref["named"][0])
    report = json.loads((rep / "sync.json").read_text())
    assert report["sync"]["time_offset_s"]["sigma"] > 0 and (rep / "sync.png").stat().st_size > 10_000


# ------------------------------------------------------------------------------------------ real logs
def real_log_flight(log_path: Path, out: Path, start_s: float, seconds: float, hfov_deg: float, mount: int,
                    log_index: int | None = None):
    """An AGC'd video of `seconds` rendered from a real log's own gyro from `start_s` into it, the camera
    mounted by rotation `mount`: (video, camera.toml, log_offset_s, camera_from_body)."""
    from thermod.sim import motion as mo
    from thermod.sim.synth import simulate

    log = flightlog.read_flight_log(log_path, log_index)
    R = flightlog.axis_aligned_rotations()[mount]
    body = mo.GyroLog(log.t, log.rate, float(log.t[0] + start_s), spec="real log")
    fx = 0.5 * WIDTH / math.tan(math.radians(hfov_deg) / 2)
    calib = Calibration().replace(width=WIDTH, height=HEIGHT, fx=fx, fy=fx, cx=(WIDTH - 1) / 2,
                                  cy=(HEIGHT - 1) / 2, frame_rate_hz=FPS, tau_s=TAU, rate_hz=log.rate_hz)
    rec = simulate("texture", MountedMotion(body, R), seconds, calib, seed=5, truth=False)
    agc = video.PercentileAGC()
    frames8 = np.stack([agc.apply(f, float(t))[0] for f, t in zip(rec.frames, rec.t, strict=True)])
    path = video.write_video(out / "video.mp4", frames8, rec.t - rec.t[0])
    t_read = video.read_video(path).t
    return path, camera_toml(out / "camera.toml", hfov_deg), log.t[0] + start_s - t_read[0], R


def test_import_with_a_real_betaflight_blackbox(tmp_path):
    """The .bbl holds two logs; the 50 s flight is the longest, the one read by default."""
    log = REAL_LOGS / "betaflight_btfl_001.bbl"
    video_path, cam, log_offset, R = real_log_flight(log, tmp_path, 24.0, 3.0, 40.0, mount=9)
    out = tmp_path / "rec.h5"
    r = thermod("import", video_path, "--gyro", log, "-o", out, "--calibration", cam, "--no-refine")
    assert r.returncode == 0, r.stderr
    check_import(out, log_offset, R, 1 / FPS)


def test_a_video_of_a_real_px4_log_at_rest_is_refused(tmp_path):
    """The PX4 sample was logged at rest: below 10 Hz its rates vary by 0.3 °/s, the rest is vibration
    a 30 fps picture cannot follow. The place of a video rendered from it is refused, not guessed."""
    log = REAL_LOGS / "px4_sample_appended_multiple.ulg"
    video_path, cam, _, _ = real_log_flight(log, tmp_path, 2.0, 6.0, 12.0, mount=9)
    out = tmp_path / "rec.h5"
    refused(thermod("import", video_path, "--gyro", log, "-o", out, "--calibration", cam, "--no-refine"),
            "video.mp4", log.name, "correlates")
    assert not out.exists()


# ------------------------------------------------------------------------------------------ refusals
def refused(r: subprocess.CompletedProcess, *words: str) -> str:
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    err = r.stderr.strip().splitlines()[-1]
    assert "Traceback" not in r.stderr and all(w in err for w in words), err
    return err


def test_refuses_bad_input(flight, tmp_path):
    sim, cam = flight
    out = tmp_path / "rec.h5"
    t = np.arange(0, 30, 1 / 50.0)
    slow = flightlog.write_gcsv(tmp_path / "slow.gcsv", t, np.zeros((len(t), 3)) + 0.1)
    refused(thermod("import", sim.video_path, "--gyro", slow, "-o", out, "--calibration", cam), "slow.gcsv",
            "100 Hz")
    t = np.arange(0, 30, 1 / 25.0)          # ArduPilot's IMU message without LOG_BITMASK's IMU_FAST bit
    slow_ap = flightlog.write_ardupilot_bin(tmp_path / "slow.bin", t, np.zeros((len(t), 3)) + 0.1)
    refused(thermod("import", sim.video_path, "--gyro", slow_ap, "-o", out, "--calibration", cam), "slow.bin",
            "25 Hz", "IMU_FAST")
    t = np.arange(0, 30, 1e-3)
    still = 0.01 + 1e-4 * np.random.default_rng(0).standard_normal((len(t), 3))     # a log at rest
    rest = flightlog.write_gcsv(tmp_path / "rest.gcsv", t, still)
    refused(thermod("import", sim.video_path, "--gyro", rest, "-o", out, "--calibration", cam, "--no-refine"),
            "rest.gcsv", "too little gyro motion")
    t = np.arange(0, 2, 1e-3)
    short = flightlog.write_gcsv(tmp_path / "short.gcsv", t, np.zeros((len(t), 3)) + 0.1)
    refused(thermod("import", sim.video_path, "--gyro", short, "-o", out, "--calibration", cam), "short.gcsv",
            "but the gyro log only", "--start S --duration D")
    log = flightlog.read_flight_log(sim.log_paths["gcsv"])           # armed 2 s into the video
    late = log.t >= sim.frame_t_video[0] + sim.log_offset_s + 2.0
    armed = flightlog.write_gcsv(tmp_path / "armed.gcsv", log.t[late], log.rate[late])
    refused(thermod("import", sim.video_path, "--gyro", armed, "-o", out, "--calibration", cam,
                    "--no-refine"), "armed.gcsv", "does not contain this video", "--start S --duration D")
    nogyro = tmp_path / "nogyro.csv"
    nogyro.write_text('"Product","Blackbox flight data recorder by Nicholas Sherlock"\n'
                      '"loopIteration","time","motor[0]"\n0,1000,1000\n1,2000,1000\n')
    refused(thermod("import", sim.video_path, "--gyro", nogyro, "-o", out, "--calibration", cam),
            "nogyro.csv")
    (tmp_path / "logs").mkdir()                  # refused before the video is read, naming the option
    refused(thermod("import", sim.video_path, "--gyro", tmp_path / "logs", "-o", out, "--calibration", cam),
            "--gyro", "logs: is a directory, expected a file")
    truncated = tmp_path / "truncated.mp4"
    data = sim.video_path.read_bytes()
    truncated.write_bytes(data[: len(data) // 3])
    refused(thermod("import", truncated, "--gyro", sim.log_paths["gcsv"], "-o", out, "--calibration", cam),
            "truncated.mp4")
    other = camera_toml(tmp_path / "other.toml", 50.0, width=320, height=240)
    refused(thermod("import", sim.video_path, "--gyro", sim.log_paths["gcsv"], "-o", out, "--calibration",
                    other), "video.mp4", "320×240")
    zero = tmp_path / "zero.toml"
    zero.write_text("[camera]\nwidth = 160\nheight = 120\nhfov_deg = 40\nframe_rate_hz = 0\ntau_s = 0.008\n")
    refused(thermod("import", sim.video_path, "--gyro", sim.log_paths["gcsv"], "-o", out, "--calibration",
                    zero), "zero.toml", "frame_rate_hz")
    stamped = tmp_path / "stamped.gcsv"
    stamped.write_text("GYROFLOW IMU LOG\nversion,1.3\nid,x\norientation,XYZ\ntscale,0.001\ngscale,1\n"
                       "t,gx,gy,gz\n" + "".join("5,0.1,0.2,0.3\n" for _ in range(200)))
    refused(thermod("import", sim.video_path, "--gyro", stamped, "-o", out, "--calibration", cam),
            "stamped.gcsv")
    refused(thermod("import", sim.video_path, "--gyro", sim.log_paths["gcsv"], "-o", out), "--camera")
    refused(thermod("import", sim.video_path, "--gyro", sim.log_paths["gcsv"], "-o", out, "--camera", "nope"),
            "boson640_14mm")
    refused(thermod("import", sim.video_path, "--gyro", sim.log_paths["gcsv"], "-o", out, "--calibration",
                    cam, "--fps", "0"), "--fps")
    refused(thermod("import", sim.video_path, "--gyro", sim.log_paths["gcsv"], "-o", out, "--calibration",
                    cam, "--start", "60"), "video.mp4", "no frame from 60 s")
    refused(thermod("import", sim.video_path, "--gyro", sim.log_paths["gcsv"], "-o", out, "--calibration",
                    cam, "--duration", "-1"), "--duration -1")
    # without --gyro a video's motion comes from its pictures (tests/motion/test_video_motion.py):
    # it still needs the camera
    refused(thermod("import", sim.video_path, "-o", out, "--start", "1"), "video.mp4", "without --gyro",
            "needs the camera")
    from thermod.ingest.flight import FlightImportError, import_flight
    from thermod.io.camera_file import load_camera
    with pytest.raises(FlightImportError, match=r"video\.mp4: .* GiB limit.* --start S --duration D"):
        import_flight(sim.video_path, sim.log_paths["gcsv"], out, load_camera(cam),
                      max_bytes=10 * WIDTH * HEIGHT)
    assert not out.exists()


def test_camera_presets_load_and_list():
    from thermod.io.camera_file import load_camera, preset_names, preset_path

    names = preset_names()
    assert "boson640_14mm" in names and len(names) >= 4
    for n in names:
        c = load_camera(preset_path(n))
        assert c.width >= 320 and 0 < c.tau_s < 0.05 and c.fx > 100
    r = thermod("import", "--list-cameras")
    assert r.returncode == 0 and r.stdout.split() == names


def test_deblur_video_of_a_16_bit_recording_uses_one_agc_for_both_halves(tmp_path):
    """A recording of raw counts (thermod sim) is shown through PercentileAGC; the deblurred half uses
    the input frame's gain and offset, so a static scene looks the same on both sides."""
    import av

    rec, deb, mp4, gcsv = (tmp_path / n for n in ("sim.h5", "deb.h5", "deb.mp4", "out.gcsv"))
    r = thermod("sim", "-o", rec, "--motion", "static", "--seconds", "0.4", "--width", 96, "--height", 64,
                "--no-progress", "--no-truth")
    assert r.returncode == 0, r.stderr
    r = thermod("deblur", rec, "-o", deb, "--video", mp4, "--side-by-side", "--uniform", "--jobs", "1")
    assert r.returncode == 0, r.stderr
    with av.open(str(mp4)) as c:
        frames = np.stack([f.to_ndarray(format="gray") for f in c.decode(video=0)]).astype(float)
    from thermod.io.recording import read
    raw = read(rec)
    assert frames.shape == (raw.n_frames, 64, 192)
    left, right = frames[:, :, :96], frames[:, :, 96:]
    assert left.std() > 20 and np.median(np.abs(left - right)[:, 8:-8, 8:-8]) < 8
    # export of a recording that was not imported: the first frame at 0 on the video clock
    assert thermod("export", rec, "--gcsv", gcsv).returncode == 0
    log = flightlog.read_flight_log(gcsv)
    assert log.t[0] >= 0 and abs(log.t[0]) < 2 / raw.calibration.rate_hz
    assert thermod("deblur", rec, "-o", tmp_path / "x.h5", "--side-by-side").returncode == 2
    # a --video name no container for H.264 takes: refused before the deblur, not after it
    for name in ("deb.gif", "deb.webm", "deb"):
        r = thermod("deblur", rec, "-o", tmp_path / "y.h5", "--video", tmp_path / name)
        assert r.returncode == 2 and f"{tmp_path / name}: cannot hold H.264" in r.stderr, r.stderr
        assert not (tmp_path / "y.h5").exists() and "Traceback" not in r.stderr

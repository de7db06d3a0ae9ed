"""Flight-like simulator recordings with no static lead-in, for the discrepancy tests (imported via
sys.path like `reference_kernels`).

`flight_recording(effects, seconds, size, seed, real_log)` renders with the simulator's independent
fine-time renderer (`thermod.sim.synth.simulate`, never `thermod.calib.forward`) a camera that is
moving from before its first frame: the real Betaflight gyro log (`sim.motion.gyro_log`, from
``seed``·0.7 s into it) when `real_log` (callers check `SHARED_DATA`/`require` first), else the
synthetic multirotor attitude `sim.motion.flight` (pitch/yaw/roll 8/15/12 °/s RMS), so a bare clone
runs too. NETD 50 mK unless `effects` says otherwise; the scene is the seeded procedural texture.
"""

from __future__ import annotations

from dataclasses import dataclass

from thermod.io.recording import Recording
from thermod.physics.calibration import Calibration
from thermod.sim import motion as mo
from thermod.sim.synth import simulate, truth_calibration


@dataclass
class FlightRecording:
    rec: Recording
    nominal: Calibration       # what the file's attributes claim (the model under test)
    truth: Calibration         # what the world was rendered with


def nominal_calibration(size=(160, 120)) -> Calibration:
    """The paper's camera scaled to `size` (width, height): same field of view, fewer pixels."""
    w, h = size
    intr = Calibration().intrinsics.scaled(w / Calibration().width)
    return Calibration(width=w, height=h, fx=intr.fx, fy=intr.fy, cx=intr.cx, cy=intr.cy)


def flight_motion(seed: int = 0, real_log: bool = False) -> mo.Motion:
    return mo.gyro_log(None, start_s=0.7 * seed + 1.0) if real_log else mo.flight(seed=seed)


def flight_recording(effects: dict | None = None, seconds: float = 0.4, size=(160, 120), seed: int = 0,
                     real_log: bool = False, scene="texture") -> FlightRecording:
    """A recording of `seconds` at `size` with hidden `effects` (the simulator's vocabulary) and flight
    motion (see the module docstring); returns it with its nominal and true calibrations."""
    nominal = nominal_calibration(size)
    rec = simulate(scene, flight_motion(seed, real_log), seconds, nominal, {"netd": 0.05, **(effects or {})},
                   seed=seed)
    return FlightRecording(rec, nominal, truth_calibration(rec))

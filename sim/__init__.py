"""The simulator: a world with known truth to test everything else against.

- `scenes`     sharp scenes in raw counts (real 16-bit frames, collimator targets, textures)
- `motion`     camera-frame angular velocity ω(t) (pan, slew, shake, vibration, a real gyro log, …)
               and its integration into orientations R(t)
- `detector`   the fine-time microbolometer (and photon-detector) renderer: the truth
- `gyro_model` raw gyro samples with a realistic error budget, in the gyro frame and clock
- `synth`      `simulate(...) -> thermod.io.recording.Recording` with hidden calibration effects
- `flight_video` a flight as other tools hand it over: AGC'd H.264 video + a gyro log in a real format
               (gcsv, Betaflight CSV, ArduPilot .bin) with a hidden time offset and camera mount
- `playback`   a pre-rendered looping sequence for the real-time simulated payload
- `payload`    the simulated payload the daemon runs on: the emulated camera and IMU playing a loop
  (`thermod sim` is `thermod.cli.sim`)
- `flight_recordings`, `sync_flights`, `reference_kernels`  builders the tests and the benchmarks
               share: flight-like recordings, sync inputs with a hidden truth, a plain NumPy kernel renderer

Submodules are imported on demand (numba compiles on first use).
"""

"""thermod's formats: recording format v1 (HDF5) and the wire v1 message codec.

`thermod.io.recording` is the one reader and writer of recordings (docs/design.md §3); it validates
everything it reads and raises `RecordingError` naming the file and field. The wire codec builds and
validates the three-part `[topic, JSON header, array bytes]` messages of docs/design.md §4 without
owning a socket. `thermod.io.video` reads and writes thermal video (PyAV/FFmpeg, TIFF sequences
through OpenCV) and `thermod.io.flightlog` reads flight-controller gyro logs (telemetry-parser,
pyulog) and writes gcsv, Betaflight CSV and ArduPilot DataFlash (docs/design.md §3, "Flights from
other tools"). Formats only: this package imports h5py, PyAV, OpenCV, telemetry-parser, pyulog,
`thermod.physics` (for `Calibration`) and `thermod.errors`, and never `thermod.runtime`,
`thermod.calib`, `thermod.cli`, `thermod.drivers`, `thermod.sim`, zmq or GStreamer — sending and
receiving belong to `thermod.runtime.publish`.
"""

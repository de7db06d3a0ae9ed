"""The mathematics of gyro-aided deblurring, as pure array functions and frozen dataclasses.

"Eq. N" throughout thermod is equation N of Lee, Ban, Kim, "Motion Blur Kernel Rendering Using an
Inertial Sensor: Interpreting the Mechanism of a Thermal Detector", Sensors 22(5), 1893, 2022,
doi:10.3390/s22051893.

Camera intrinsics, SO(3) maps and the rotation-only homography (Eq. 16), the `Calibration` that every
other part shares (with the optical PSF of Eq. 19), the microbolometer's thermal IIR (Eq. 10/11), the
blur-kernel renderer (thermal Eq. 18 and photon Eq. 17, in numba) and the non-blind deconvolution
(Krishnan & Fergus, Wiener, tiles). docs/design.md §1 explains the physics. This is the bottom layer:
it imports numpy, scipy, numba, OpenCV and optionally pyFFTW, and from thermod only `thermod.errors` —
never `thermod.io`, `thermod.runtime`, `thermod.calib`, `thermod.cli`, `thermod.drivers`,
`thermod.sim`, h5py, zmq or GStreamer — so it can be tested and reused without files, devices or a
network.
"""

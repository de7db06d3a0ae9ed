"""Motion from the pictures alone: the camera's rotation between frames (`picture`), a camera's
automatic gain control undone once that rotation is known (`agc`), and a video's whole rotation track
turned into a gyro (`track`). The sync to a gyro log and the video-only import build on it; it needs
no gyro and no transport, only `thermod.physics` and `thermod.io`."""

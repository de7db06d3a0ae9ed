"""Motion from the pictures alone: the camera's rotation between frames (`picture`) and a camera's
automatic gain control undone once that rotation is known (`agc`). The sync to a gyro log builds on
it; it needs no gyro and no transport, only `thermod.physics` and `thermod.io`."""

"""Shared by the camera-source tests (tests/drivers/test_v4l2.py, tests/sim/test_sim_camera.py)."""


def poll_frames(cam, n: int, timeout: float = 30.0) -> list:
    """The next ``n`` frames of a started camera source. ``poll`` returns as soon as a frame is there;
    the timeout only catches a hang (a loaded machine may be slow, never a source that stopped)."""
    out = []
    for _ in range(n):
        f = cam.poll(timeout)
        assert f is not None, f"{cam.name}: frame {len(out) + 1} of {n} did not come within {timeout} s"
        out.append(f)
    return out

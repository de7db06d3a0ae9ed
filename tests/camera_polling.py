"""Shared by the camera-source tests (imported from beside them, like reference_kernels)."""


def poll_frames(cam, n: int, timeout: float = 0.5) -> list:
    """The next ``n`` frames of a started camera source; each must come within ``timeout`` seconds."""
    out = []
    for _ in range(n):
        f = cam.poll(timeout)
        assert f is not None, f"{cam.name}: frame {len(out) + 1} of {n} did not come within {timeout} s"
        out.append(f)
    return out

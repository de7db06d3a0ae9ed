"""Deconvolution at half resolution (`thermod.physics.deconv.half`), the governor's last rung: the
kernel's displacements halved, the frame averaged over 2×2 blocks, and a result far closer to the
truth than the blurry frame it replaces."""

import numpy as np
import pytest

from thermod.physics.deconv import Deconvolver
from thermod.physics.deconv.half import HalfResolution, halve_kernel
from thermod.physics.kernels import Kernel, blur
from thermod.sim.kernels import comet
from thermod.sim.scenes import texture


def centroid(w, origin):
    iy, ix = np.indices(w.shape)
    s = w.sum()
    return (float((w * (iy - origin[0])).sum() / s), float((w * (ix - origin[1])).sum() / s))


@pytest.mark.parametrize("kernel", [
    Kernel(np.full((1, 9), 1 / 9, np.float32), (0, 0)),          # a box smear 8 px to the right
    comet(17, 17 / 4, 30.0),                                      # a thermal comet at 30°
    Kernel(np.ones((1, 1), np.float32), (0, 0)),                  # no motion
])
def test_halved_kernel_moves_half_as_far_and_keeps_its_weight(kernel):
    half = halve_kernel(kernel)
    assert half.weights.dtype == np.float32 and half.weights.sum() == pytest.approx(1.0, abs=1e-5)
    cy, cx = centroid(kernel.weights, kernel.origin)
    hy, hx = centroid(half.weights, half.origin)
    assert hy == pytest.approx(cy / 2, abs=1e-4) and hx == pytest.approx(cx / 2, abs=1e-4)
    assert max(half.weights.shape) <= max(kernel.weights.shape) // 2 + 2


def psnr(x, truth):
    lo, hi = np.percentile(truth, (0.5, 99.5))
    return 10 * np.log10((hi - lo) ** 2 / np.mean((x.astype(np.float64) - truth) ** 2))


def test_half_resolution_deblurs_far_above_the_blurry_frame():
    rng = np.random.default_rng(1)
    scene = texture(400, 520, seed=3)
    k = comet(21, 21 / 4, 20.0)
    truth = scene[60:-60, 60:-60]
    lo, hi = np.percentile(truth, (0.5, 99.5))
    b = blur(scene, k)[60:-60, 60:-60] + rng.normal(0, 0.004 * (hi - lo), truth.shape).astype(np.float32)
    d = HalfResolution(Deconvolver(method="wiener"))
    out = d.run(b, k)
    assert out.shape == b.shape and out.dtype == np.float32 and d.last_cells == 1
    assert psnr(out, truth) > psnr(b, truth) + 3.0, (psnr(out, truth), psnr(b, truth))
    assert np.isfinite(d.last_lam)                # the wrapped solver's λ, as a caller books it


def test_a_grid_is_solved_with_its_central_kernel():
    class Grid:
        pass

    rng = np.random.default_rng(2)
    img = rng.normal(1000, 20, (120, 160)).astype(np.float32)
    g = Grid()
    k = comet(9, 2.0, 0.0)
    other = Kernel(np.ones((1, 1), np.float32), (0, 0))
    g.kernels = [[other, other, other], [other, k, other], [other, other, other]]
    g.centers = np.array([[(y, x) for x in (26.5, 79.5, 132.5)] for y in (19.5, 59.5, 99.5)])
    d = HalfResolution(Deconvolver(method="wiener"))
    np.testing.assert_array_equal(d.run_varying(img, g), d.run(img, k))

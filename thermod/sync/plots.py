"""The sync's figure: picture rate against gyro rate before and after, and the whole-log correlation."""

from __future__ import annotations

import math

import numpy as np

from thermod.sync.coarse import MOUNTS
from thermod.sync.fine import FineProblem
from thermod.sync.result import SyncResult


def plot_sync(result: SyncResult, gyro_t, gyro_rate, path) -> None:
    """PNG: the picture's rotation rate against the gyro's, per camera axis, before sync (the log as
    recorded, its first sample at the first frame) and after (rotated into the camera frame by
    R_cam_gyro, bias removed, shifted by the offset, through τ and averaged over each frame interval
    as the picture sees it); below, the correlation over the log for the chosen and the runner-up
    mount."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    gt = np.asarray(gyro_t, np.float64)
    gr = np.asarray(gyro_rate, np.float64)
    pm, fine, coarse = result.picture, result.fine, result.coarse
    naive_offset = float(pm.t0[0] - gt[0])
    after = FineProblem(pm, gt, gr, fine.time_offset_s, result.tau_s, fine.readout_s)
    x_after = np.r_[fine.time_offset_s, fine.misalignment_rad, fine.bias_rad_s, 1e-6 * fine.clock_drift_ppm]
    rate_after = after.predicted(x_after, MOUNTS[fine.mount_index]) / after.dts[:, None]
    before = FineProblem(pm, gt, gr, naive_offset, 0.0, 0.0)
    rate_before = before.predicted(np.r_[naive_offset, np.zeros(7)], np.eye(3)) / before.dts[:, None]
    tm = 0.5 * (after.t0 + after.t1) - pm.t0[0]
    pic = after.phi / after.dts[:, None]
    fig = plt.figure(figsize=(12, 9), constrained_layout=True)
    grid = fig.add_gridspec(4, 2)
    deg = 180.0 / math.pi
    for col, (label, g) in enumerate((("before sync (log as recorded, same start)", rate_before),
                                      (f"after sync (offset {fine.time_offset_s:.4f} s, mount "
                                       f"{MOUNTS[fine.mount_index].astype(int).tolist()})", rate_after))):
        for a, name in enumerate(("x (right)", "y (down)", "z (forward)")):
            ax = fig.add_subplot(grid[a, col])
            ax.plot(tm, pic[:, a] * deg, ".-", ms=3, lw=0.8, label="picture")
            ax.plot(tm, g[:, a] * deg, lw=1.0, label="gyro")
            ax.set_ylabel(f"ω {name} (°/s)")
            if a == 0:
                ax.set_title(label, fontsize=10)
                ax.legend(loc="upper right", fontsize=8)
            if a == 2:
                ax.set_xlabel("video time (s)")
    ax = fig.add_subplot(grid[3, :])
    ax.plot(coarse.lags_s, coarse.ncc_curves[fine.mount_index], lw=0.8, label=f"mount {fine.mount_index}")
    ax.plot(coarse.lags_s, coarse.ncc_curves[coarse.second_mount_index], lw=0.8, alpha=0.7,
            label=f"runner-up mount {coarse.second_mount_index}")
    ax.axvline(fine.time_offset_s, color="k", lw=0.6, ls="--")
    ax.set_xlabel("time offset t_cam − t_gyro (s)")
    ax.set_ylabel("normalised correlation")
    ax.set_title(f"whole-log correlation: peak {coarse.ncc:.3f}, elsewhere {coarse.ncc_elsewhere:.3f}, "
                 f"runner-up mount {coarse.ncc_second_mount:.3f}", fontsize=10)
    ax.legend(loc="lower right", fontsize=8)
    fig.savefig(path, dpi=90)
    plt.close(fig)

"""Restoring frames: the settings of a restoration and the kernel planning behind it.

Above the core (`thermod.physics`, `thermod.io`, `thermod.calib`) and below every user of it: the
daemon (`thermod.runtime`) and offline deblurring (`thermod.batch`, `thermod deblur`) both plan a
frame's kernel here, so a recording deblurred offline and the same frames deblurred live agree.
"""

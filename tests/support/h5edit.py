"""A recording copied and changed in place: the way the bad-input tests break one field of it."""

import shutil

import h5py


def edited_copy(src, dst, edit):
    """`src` copied to `dst`, then `edit(f)` on the copy open for writing (h5py); returns `dst`."""
    shutil.copy(src, dst)
    with h5py.File(dst, "r+") as f:
        edit(f)
    return dst

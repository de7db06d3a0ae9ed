"""Detector-side effects of the model under test: what happens to the counts after the thermal IIR.

* `Response` — a non-linear response of the counts (`detector_nonlinearity`), written as the
  radiometric *linearisation* a user would apply: ``x = L(y) = c0 + (y − c0) + γ (y − c0)²`` maps raw
  counts y to counts linear in the flux about the level c0. The blur (warp + IIR, Eq. 10/11/16) acts on
  the linear x, so a frame is predicted as ``y = L⁻¹(P(L(r)))`` with r the reference minus its FPN.
  The forward model P is linear in its reference, so ``P(L(r)) = P(r) + γ P((r − c0)²)``: one extra
  prediction of the squared reference serves every γ, and L⁻¹ is closed-form. Its residual under a
  linear model is ``≈ γ·(P(r²) − P(r)²)``, γ times the variance the blur kernel mixes (Jensen's gap):
  one sign everywhere, unlike the zero-mean residuals of τ or an extra PSF.
* `FFCEvent` — a flat-field correction (shutter / NUC, `ffc_event`, the daemon's ``ffc`` pass-through
  reason): frames read in [t_start, t_end) repeat the last frame read before it; frames after it carry
  the new NUC, a global offset `step_counts` plus a high-pass FPN change estimated per segment like
  the FPN itself (`estimate_fpn`).

`predict(d, model)` is the one prediction every cost, FPN estimate and mask goes through.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class Response:
    """Linearisation ``x = c0 + u + γ u²``, u = y − c0 (counts; γ per count)."""

    level: float
    gamma: float

    def linearise(self, y):
        u = np.asarray(y, np.float32) - np.float32(self.level)
        return self.level + u + np.float32(self.gamma) * u * u

    def counts(self, x):
        """L⁻¹: u = 2v / (1 + √(1 + 4γv)), v = x − c0 (stable at γ → 0; clipped where L has no inverse)."""
        v = np.asarray(x, np.float32) - np.float32(self.level)
        root = np.sqrt(np.maximum(1.0 + np.float32(4.0 * self.gamma) * v, 0.0))
        return (np.float32(self.level) + 2.0 * v / (1.0 + root)).astype(np.float32)


@dataclass(frozen=True)
class FFCEvent:
    """One flat-field correction in recording `recording` (camera clock, s)."""

    recording: str
    t_start: float
    t_end: float
    step_counts: float = 0.0

    def frozen(self, frame_t) -> np.ndarray:
        t = np.asarray(frame_t)
        return (t >= self.t_start) & (t < self.t_end)

    def after(self, frame_t) -> np.ndarray:
        return np.asarray(frame_t) >= self.t_end

    def last_live(self, frame_t) -> int:
        """Index of the last motion frame read before the event (−1: it repeats a static frame)."""
        return int(np.searchsorted(np.asarray(frame_t), self.t_start, side="left")) - 1


def events_of(d, model) -> list[FFCEvent]:
    return sorted((e for e in getattr(model, "ffc", ()) if e.recording == d.name), key=lambda e: e.t_start)


def _squared_reference_model(d, level: float):
    """A copy of d's forward model whose reference is (r − c0)² (same grid; its own view cache)."""
    # (the key is the reference array itself: every set_reference makes a new one)
    key = (id(d.fm.reference), level)
    aux = d.aux.get("response_fm")
    if aux is None or aux[0] != key or aux[2] is not d.fm.reference:
        fm2 = copy.copy(d.fm)
        # same canvas placement and support (a motion-only recording's scene canvas), no FPN; 0 outside
        # the support (the canvas is 0 there, c0² would leak into every view that touches its edge)
        support = getattr(d.fm, "support", None)
        sq = (d.fm.reference - np.float32(level)) ** 2
        if support is not None:
            sq = sq * (support > 0)
        fm2.set_reference(sq, None, prescaled=True, origin=getattr(d.fm, "origin", (0.0, 0.0)),
                          support=support)
        aux = (key, fm2, d.fm.reference)
        d.aux["response_fm"] = aux
    return aux[1]


def mixing_variance(d, model, pred_linear: np.ndarray | None = None) -> np.ndarray:
    """P(r²) − P(r)²: the variance of the reference the blur mixes into each predicted pixel (counts²)."""
    c = float(np.mean(d.fm.reference))
    p2, _ = _squared_reference_model(d, c).predict(model.calib, model.extra_psf_px)
    if pred_linear is None:
        pred_linear, _ = d.fm.predict(model.calib, model.extra_psf_px)
        if d.fm.fpn is not None:
            pred_linear = pred_linear - d.fm.fpn[None]
    return np.maximum(p2 - (pred_linear - np.float32(c)) ** 2, 0.0)


def respond(d, model, p: np.ndarray) -> np.ndarray:
    """A linear prediction `p` of `d.fm` (FPN included) through the model's response, if it has one."""
    resp = getattr(model, "response", None)
    if resp is None or resp.gamma == 0.0:
        return p
    fpn = d.fm.fpn if d.fm.fpn is not None else np.float32(0.0)
    p2, _ = _squared_reference_model(d, resp.level).predict(model.calib, model.extra_psf_px)
    return resp.counts(p - fpn + np.float32(resp.gamma) * p2) + fpn


def predict(d, model):
    """Predicted motion frames (counts, FPN included) and their valid mask, with the detector effects."""
    p, v = d.fm.predict(model.calib, model.extra_psf_px)
    p = respond(d, model, p)
    events = events_of(d, model)
    if events:
        steps = d.aux.get("ffc_fpn")
        for i, e in enumerate(events):
            frozen, last = e.frozen(d.frame_t), e.last_live(d.frame_t)
            if frozen.any():
                p[frozen] = p[last] if last >= 0 else d.static_mean
                v[frozen] = v[last] if last >= 0 else True
            after = e.after(d.frame_t)
            p[after] += np.float32(e.step_counts)
            if steps is not None and i < len(steps) and steps[i] is not None:
                p[after] += steps[i]
    return p, v


def segments(d, model) -> np.ndarray:
    """Per motion frame: −1 frozen, else the number of FFC events before it (0 = the reference's NUC)."""
    seg = np.zeros(len(d.frame_t), int)
    for e in events_of(d, model):
        seg[e.after(d.frame_t)] += 1
    for e in events_of(d, model):
        seg[e.frozen(d.frame_t)] = -1
    return seg


def add_segment_fpn(r, v, seg, n_seg: int, highpass_px: float, F, steps: list):
    """One update of the fixed-pattern noise per flat-field segment from the residual `r` (frames ×
    H × W, valid where `v`; `seg` gives each frame's segment): the high-passed temporal mean of each
    segment's residual is added to `F` (segment 0) or to `steps[s − 1]` (the offset a correction
    left after event s, updated in place). Returns the new F."""
    for s in range(n_seg):
        sel = seg == s
        cnt = v[sel].sum(axis=0)
        upd = np.where(cnt > 0, r[sel].sum(axis=0) / np.maximum(cnt, 1), 0.0).astype(np.float32)
        upd -= cv2.GaussianBlur(upd, (0, 0), highpass_px, borderType=cv2.BORDER_REPLICATE)
        if s == 0:
            F = F + upd
        else:
            steps[s - 1] = upd if steps[s - 1] is None else steps[s - 1] + upd
    return F


def estimate_fpn(d, model, iters: int, highpass_px: float) -> np.ndarray:
    """FPN of the reference's NUC segment, and (in d.aux["ffc_fpn"]) the change after each FFC event.

    FPN stays put on the sensor while the scene moves, so it is what the motion residual has in common
    over time: F ← F + HP(mean_k r_k), from F = 0 under the current model, frozen frames left out.
    Only the high-pass part is kept: low spatial frequencies are nearly the same in the reference and
    the moved views and would absorb slow model errors instead. After an FFC the new NUC's pattern is
    estimated the same way from that segment's frames (its global offset is the event's step_counts).
    """
    seg = segments(d, model)
    n_seg = int(seg.max()) + 1 if len(seg) else 1
    F = np.zeros_like(d.static_mean)
    steps: list = [None] * (n_seg - 1)
    for _ in range(iters):
        d.fm.set_reference(d.static_mean, F, prescaled=True)
        d.aux["ffc_fpn"] = steps
        p, v = predict(d, model)
        F = add_segment_fpn(np.where(v, d.measured - p, 0.0), v, seg, n_seg, highpass_px, F, steps)
    d.aux["ffc_fpn"] = steps
    return F


def temporal_change(d, frames: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per motion frame, the mean square change from the frame before (the first: from the static
    reference) over the pixels valid in both, and what noise alone gives there (counts²)."""
    n = len(frames)
    change, noise = np.zeros(n), np.zeros(n)
    for k in range(n):
        prev, mprev = (frames[k - 1], mask[k - 1]) if k else (d.static_mean, mask[k])
        m = mask[k] & mprev
        if m.any():
            change[k] = float(np.mean((frames[k][m].astype(np.float64) - prev[m]) ** 2))
        noise[k] = d.noise_var * (2.0 if k else 1.0 + 1.0 / max(d.n_static, 1))
    return change, noise


def detect_frozen(d, predicted: np.ndarray, mask: np.ndarray, *, min_motion: float = 4.0,
                  max_change: float = 0.5) -> np.ndarray:
    """Motion frames that did not change although the model says the image moved: a camera holding its
    output during a flat-field correction repeats the last frame, so its change is far below what the
    temporal noise alone gives a live frame (< `max_change` × noise), where the model predicts a change
    above `min_motion` × noise. Testing against the noise, not against the predicted change, keeps
    frames that moved less than predicted (a time offset at the motion onset) live."""
    dm, noise = temporal_change(d, d.measured, mask)
    dp, _ = temporal_change(d, predicted, mask)
    return (dp > min_motion * noise) & (dm < max_change * noise)


def frozen_runs(frozen: np.ndarray) -> list[tuple[int, int]]:
    """(first, last + 1) of each run of True."""
    edges = np.flatnonzero(np.diff(np.r_[0, frozen.astype(np.int8), 0]))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True))

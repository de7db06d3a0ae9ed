"""Counts → temperature (°C): the two camera models thermod applies after deblurring.

Deblurring works on counts because they are linear in the flux on the detector (the blur is a
weighted sum of fluxes, Eq. 18); a temperature is a non-linear function of flux, so a frame is
deblurred first and converted after (docs/design.md, physics).

- `Planck`: FLIR's radiometric calibration, as FLIR GigE cameras expose it over GenICam (features
  ``R``, ``B``, ``F``, ``O``): ``S = R / (exp(B / T) − F) + O`` for a blackbody at T kelvin, so
  ``T = B / ln(R / (S − O) + F)``. No emissivity, atmosphere or reflected-temperature correction:
  the result is the apparent (blackbody) temperature the camera's own constants give.
- `Linear`: ``°C = gain · counts + offset`` (e.g. a camera in a "temperature linear" output mode:
  gain 0.01 or 0.1 K/count, offset −273.15).

Both are frozen dataclasses that check themselves (`RadiometryError` names the field) and convert
with ``to_celsius(counts) -> float32``. `from_mapping` builds either one from a ``model = …``
table (a config's ``[radiometry]``, a recording's ``/radiometry`` attributes); `as_dict` is its
inverse. numpy only.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import MISSING, dataclass, fields
from typing import Any

import numpy as np

from thermod.errors import ThermodError

KELVIN_AT_0C = 273.15
MODELS = ("planck", "linear")
# The recording group whose attributes carry a model (same keys as a config's [radiometry] table)
RECORDING_GROUP = "radiometry"


class RadiometryError(ThermodError, ValueError):
    """A radiometric constant is missing, not a number or out of its range. `field` names it."""

    def __init__(self, field: str, problem: str):
        self.field, self.problem = field, problem
        super().__init__(f"radiometry.{field}: {problem}")


def _finite(name: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise RadiometryError(name, f"expected a number, got {v!r}")
    v = float(v)
    if not math.isfinite(v):
        raise RadiometryError(name, f"expected a finite number, got {v!r}")
    return v


@dataclass(frozen=True)
class Planck:
    """FLIR Planck constants: ``T[K] = B / ln(R / (S − O) + F)``, S the signal in counts.

    R > 0 (counts·…), B > 0 (K), F ≥ 0, O (counts) any finite value. Pixels with no temperature under
    the model come out NaN, never a warning: S ≤ O (at or below the zero-radiance offset) and, when
    F < 1, S − O ≥ R / (1 − F) (the log's argument ≤ 1: beyond the curve's saturation).
    """

    R: float
    B: float
    F: float = 1.0
    O: float = 0.0  # noqa: E741 - FLIR's name for the offset

    model = "planck"

    def __post_init__(self):
        for f in fields(self):
            object.__setattr__(self, f.name, _finite(f.name, getattr(self, f.name)))
        if not self.R > 0:
            raise RadiometryError("R", f"expected > 0, got {self.R!r}")
        if not self.B > 0:
            raise RadiometryError("B", f"expected > 0 (kelvin), got {self.B!r}")
        if not self.F >= 0:
            raise RadiometryError("F", f"expected ≥ 0, got {self.F!r}")

    def to_kelvin(self, counts) -> np.ndarray:
        """Apparent temperature in K (float64); NaN where the model has none (see the class)."""
        return self._kelvin(counts, np.float64)

    def to_celsius(self, counts) -> np.ndarray:
        """°C as float32, same shape as ``counts``. Computed in float32 (a 640×480 frame in a few ms,
        on the daemon's publishing path): ≤ 1e-4 K from the float64 result over the camera's range."""
        t = self._kelvin(counts, np.float32)
        t -= np.float32(KELVIN_AT_0C)
        return t

    def _kelvin(self, counts, dtype) -> np.ndarray:
        c = np.asarray(counts)
        # S − O in the input's precision when it is wider (float64 counts a fraction above O), then in place
        s = np.empty(c.shape, dtype)
        np.subtract(c, self.O, out=s, dtype=np.result_type(c.dtype, dtype), casting="same_kind")
        below = ~(s > 0)                               # S ≤ O: at or below the zero-radiance offset
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            np.divide(dtype(self.R), s, out=s)
            s += dtype(self.F)
            np.log(s, out=s)                           # (log1p would cost twice as much)
            beyond = ~(s > 0)                          # log argument ≤ 1 (F < 1): past saturation
            np.divide(dtype(self.B), s, out=s)
        s[below | beyond] = np.nan
        return s

    def to_counts(self, celsius) -> np.ndarray:
        """The inverse, ``S = R / (exp(B / T) − F) + O`` (float64); NaN where no signal gives T."""
        t = np.asarray(celsius, dtype=np.float64) + KELVIN_AT_0C
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            denom = np.exp(self.B / t) - self.F
            s = self.R / denom + self.O
        return np.where((t > 0) & (denom > 0) & np.isfinite(s), s, np.nan)

    def as_dict(self) -> dict:
        return {"model": self.model, "R": self.R, "B": self.B, "F": self.F, "O": self.O}


# A linear output mode's scale is 0.01–0.1 K per count; these bounds keep °C of any 16-bit count finite
MAX_LINEAR_GAIN = 1e3
MAX_LINEAR_OFFSET = 1e4


@dataclass(frozen=True)
class Linear:
    """``°C = gain · counts + offset``; gain ≠ 0 (°C per count), offset (°C)."""

    gain: float
    offset: float = 0.0

    model = "linear"

    def __post_init__(self):
        for f in fields(self):
            object.__setattr__(self, f.name, _finite(f.name, getattr(self, f.name)))
        if not 0 < abs(self.gain) <= MAX_LINEAR_GAIN:
            raise RadiometryError("gain", f"expected a non-zero number of at most ±{MAX_LINEAR_GAIN:g} °C "
                                          f"per count, got {self.gain!r}")
        if not abs(self.offset) <= MAX_LINEAR_OFFSET:
            raise RadiometryError("offset", f"expected at most ±{MAX_LINEAR_OFFSET:g} °C, "
                                            f"got {self.offset!r}")

    def to_celsius(self, counts) -> np.ndarray:
        """°C as float32, same shape as ``counts``."""
        c = np.array(counts, dtype=np.float64)
        c *= self.gain
        c += self.offset
        return c.astype(np.float32)

    def to_counts(self, celsius) -> np.ndarray:
        return (np.asarray(celsius, dtype=np.float64) - self.offset) / self.gain

    def as_dict(self) -> dict:
        return {"model": self.model, "gain": self.gain, "offset": self.offset}


Radiometry = Planck | Linear
_KEYS = {"planck": (Planck, ("R", "B", "F", "O")), "linear": (Linear, ("gain", "offset"))}


def from_mapping(table: Mapping) -> Radiometry | None:
    """A model from ``{"model": "planck", "R": …, …}`` (None for ``model = "none"``).

    Constants with a default (F = 1, O = 0, offset = 0) may be omitted; any key the model does not use
    is an error, so a typo never silently falls back to a default.
    """
    model = table.get("model")
    if isinstance(model, bytes):
        model = model.decode("utf-8", "replace")
    if model == "none":
        rest = sorted(k for k in table if k != "model")
        if rest:
            raise RadiometryError(rest[0], "unused with model = 'none'")
        return None
    if model not in _KEYS:
        choices = ", ".join(map(repr, ("none", *MODELS)))
        raise RadiometryError("model", f"expected one of {choices}, got {model!r}")
    cls, keys = _KEYS[model]
    unknown = sorted(k for k in table if k != "model" and k not in keys)
    if unknown:
        raise RadiometryError(unknown[0], f"unknown key for model = {model!r} (expected {', '.join(keys)})")
    missing = [f.name for f in fields(cls) if f.default is MISSING and f.name not in table]
    if missing:
        raise RadiometryError(missing[0], f"missing (model = {model!r} needs {', '.join(keys)})")
    kw = {k: np.asarray(v).item() if isinstance(v, np.ndarray) and v.size == 1 else v
          for k, v in table.items() if k != "model"}
    return cls(**kw)

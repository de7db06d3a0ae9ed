"""Checked reading of TOML tables: every problem is one `ConfigError` that names the file, the dotted
key (e.g. ``deblur.lambda``) and what was expected. The daemon's configuration
(`thermod.runtime.config`) and the calibration files (`thermod.io.calibration_file`) read through it.
"""

from __future__ import annotations

import math
import os
import tomllib
from pathlib import Path
from typing import Any

from thermod.errors import ConfigError


class Section:
    """Pops and checks the keys of one TOML table; `done()` rejects whatever is left."""

    def __init__(self, path: str, prefix: str, table: Any):
        self.path, self.prefix = path, prefix
        if not isinstance(table, dict):
            raise ConfigError(f"{path}: {prefix}: expected a table, got {type_name(table)}")
        self.t = dict(table)

    def key(self, k: str) -> str:
        return f"{self.prefix}.{k}" if self.prefix else k

    def fail(self, k: str, expected: str, got: Any = None, show_got: bool = True) -> ConfigError:
        extra = f", got {got!r}" if show_got else ""
        return ConfigError(f"{self.path}: {self.key(k)}: expected {expected}{extra}")

    def has(self, k: str) -> bool:
        return k in self.t

    def pop(self, k, default, kind, *, lo=None, hi=None, lo_open=False, choices=None, required=False):
        if k not in self.t:
            if required:
                raise ConfigError(f"{self.path}: {self.key(k)}: missing (expected {describe(kind)})")
            return default
        v = self.t.pop(k)
        if kind is float and isinstance(v, int) and not isinstance(v, bool):
            v = float(v)
        if kind is bool and not isinstance(v, bool) or kind is not bool and isinstance(v, bool) \
                or not isinstance(v, kind):
            raise self.fail(k, describe(kind), v)
        if kind is float and not math.isfinite(v):
            raise self.fail(k, "a finite number", v)
        if choices is not None and v not in choices:
            raise self.fail(k, "one of " + ", ".join(repr(c) for c in choices), v)
        if lo is not None and (v <= lo if lo_open else v < lo) or hi is not None and v > hi:
            rng = f"{'(' if lo_open else '['}{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}]"
            raise self.fail(k, f"a value in {rng}", v)
        return v

    def pop_floats(self, k, default, n_allowed: tuple[int, ...], *, positive=False):
        if k not in self.t:
            return default
        v = self.t.pop(k)
        ok = isinstance(v, list) and len(v) in n_allowed and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)
        if not ok or positive and any(x <= 0 for x in v):
            what = " or ".join(str(n) for n in n_allowed)
            raise self.fail(k, f"an array of {what} {'positive ' if positive else ''}numbers", v)
        return tuple(float(x) for x in v)

    def pop_file(self, k, default=None, *, required=False, must_exist=True, what="file"):
        v = self.pop(k, default, str, required=required)
        if v is None:
            return None
        p = os.path.expanduser(v)
        if not os.path.isabs(p) and not p.startswith("/dev/"):
            p = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(self.path)), p)) \
                if not self.path.startswith("<") else os.path.abspath(p)
        if "\0" in p:
            raise self.fail(k, "a path without NUL characters", v)
        if must_exist and not os.path.exists(p):
            raise ConfigError(f"{self.path}: {self.key(k)}: {what} {p!r} does not exist")
        return p

    def done(self) -> None:
        if self.t:
            k = sorted(self.t)[0]
            raise ConfigError(f"{self.path}: {self.key(k)}: unknown key")


def type_name(v) -> str:
    """How an error message names the TOML type of `v`."""
    return {bool: "a boolean", int: "an integer", float: "a number", str: "a string", list: "an array",
            dict: "a table"}.get(type(v), type(v).__name__)


def describe(kind) -> str:
    """How an error message names what a key of Python type `kind` expects."""
    return {bool: "true or false", int: "an integer", float: "a number", str: "a string"}.get(kind, str(kind))


def read_toml(p: Path) -> dict:
    """The parsed TOML file at `p`; a missing or unreadable file is a ConfigError naming it."""
    name = str(p)
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"{name}: no such configuration file") from None
    except OSError as e:
        raise ConfigError(f"{name}: cannot read: {e.strerror or e}") from None
    return loads(data, name)


def loads(data: bytes | str, name: str = "<memory>") -> dict:
    """Parse TOML text (bytes must be UTF-8); every problem is a ConfigError naming `name` and where."""
    if isinstance(data, bytes):
        try:
            data = data.decode("utf-8")
        except UnicodeDecodeError as e:
            line = data[:e.start].count(b"\n") + 1
            raise ConfigError(f"{name}: line {line}: expected UTF-8 text, got byte 0x{data[e.start]:02x} "
                              f"at offset {e.start}") from None
    try:
        return tomllib.loads(data)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{name}: not valid TOML: {e}") from None
    except RecursionError:
        raise ConfigError(f"{name}: not valid TOML: arrays or tables nested too deeply") from None

"""Checked reading of TOML tables against a declared schema.

A table's schema is a mapping of TOML key → `Key` (type, default, range or choices, doc). Dataclasses
declare theirs with `setting`, which puts the default in the field and the rest in its metadata, so
`schema_of` reads both from one declaration. `Section.read` checks a table against a schema.

Problems are collected, not raised one by one: every bad key of a document lands in one `Problems`,
which raises a single `ConfigError` listing them all, one line each, as ``SOURCE: dotted.key: what was
expected``. SOURCE is the file, or the ``--set KEY=VALUE`` that supplied the value. An unknown key is
reported with the nearest known key (difflib) as a suggestion.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from thermod.errors import ConfigError
from thermod.paths import input_problem

REQUIRED = object()        # `Key.default` of a key the table must give
MAX_TOML_BYTES = 16 * 2**20  # a TOML file read whole: a configuration or camera file is a few kB


@dataclass(frozen=True)
class Key:
    """One key of a TOML table.

    `type` is bool, int, float, str or tuple (an array: `length` allowed lengths of `item` values).
    Numbers lie in [lo, hi] (``lo_open``: (lo, hi]); `choices` lists the allowed values. `file` names
    what a path key points at (its path is made absolute relative to the file and must exist).
    `attr` is the dataclass attribute when it differs from the TOML key (``lambda`` → ``lam``).
    """

    type: type
    default: Any = None
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    choices: tuple | None = None
    doc: str = ""
    attr: str | None = None
    file: str | None = None
    length: tuple[int, ...] = ()
    item: type = float
    positive: bool = False
    rule: Callable[[Any], str | None] | None = None    # a further check: None, or what was expected
    accepts: str = ""                # what the key accepts, when `rule` decides it

    def expected(self) -> str:
        """What this key accepts, as an error message says it."""
        if self.type is tuple:
            n = " or ".join(str(n) for n in self.length)
            what = "integers" if self.item is int else "numbers"
            rng = f" in {self.range()}" if self.lo is not None or self.hi is not None else ""
            return f"an array of {n} {'positive ' if self.positive else ''}{what}{rng}"
        if self.accepts:
            return self.accepts
        if self.file is not None:
            return f"a path ({self.file})"
        if self.choices is not None:
            return "one of " + ", ".join(repr(c) for c in self.choices)
        if self.lo is not None or self.hi is not None:
            return f"a value in {self.range()}"
        return describe(self.type)

    def range(self) -> str:
        lo = "-inf" if self.lo is None else self.lo
        hi = "inf" if self.hi is None else self.hi
        return f"{'(' if self.lo_open else '['}{lo}, {hi}]"

    def check(self, v: Any) -> tuple[Any, str | None]:
        """(the value as stored, None) or (None, what was expected instead)."""
        if self.type is tuple:
            return self._check_array(v)
        if self.type is float and isinstance(v, int) and not isinstance(v, bool):
            v = float(v)
        if isinstance(v, bool) != (self.type is bool) or not isinstance(v, self.type):
            return None, f"expected {describe(self.type)}, got {v!r}"
        # +inf only where the key's range reaches it (a replay's ``speed = inf``: as fast as possible)
        if self.type is float and not math.isfinite(v) and not (v == math.inf and self.hi == math.inf):
            return None, f"expected a finite number, got {v!r}"
        if self.choices is not None and v not in self.choices:
            return None, f"expected {self.expected()}, got {v!r}"
        if not self._in_range(v):
            return None, f"expected a value in {self.range()}, got {v!r}"
        if self.rule is not None and (expected := self.rule(v)) is not None:
            return None, f"expected {expected}, got {v!r}"
        return v, None

    def _in_range(self, v) -> bool:
        lo_bad = self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo)
        return not (lo_bad or self.hi is not None and v > self.hi)

    def _check_array(self, v) -> tuple[Any, str | None]:
        def ok_item(x):
            if isinstance(x, bool) or not isinstance(x, (int, float) if self.item is float else int):
                return False
            return math.isfinite(x) and (not self.positive or x > 0) and self._in_range(x)
        if not (isinstance(v, list) and len(v) in self.length and all(ok_item(x) for x in v)):
            return None, f"expected {self.expected()}, got {v!r}"
        return tuple(self.item(x) for x in v), None


def setting(default: Any = REQUIRED, type: type | None = None, **rules) -> Any:
    """A dataclass field whose default and TOML schema (`Key` rules: lo, hi, choices, doc, ...) are
    declared together; the type defaults to the default's."""
    kind = type if type is not None else builtin_type(default)
    key = Key(kind, default, **rules)
    if default is REQUIRED:
        return dataclasses.field(metadata={"key": key})
    return dataclasses.field(default=default, metadata={"key": key})


def builtin_type(v) -> type:
    return tuple if isinstance(v, tuple) else next(t for t in (bool, int, float, str) if isinstance(v, t))


def schema_of(cls) -> dict[str, Key]:
    """TOML key → `Key` of a dataclass declared with `setting` (fields without one are not in TOML)."""
    out = {}
    for f in dataclasses.fields(cls):
        if "key" in f.metadata:
            k = f.metadata["key"]
            out[f.name] = k if k.attr is not None else dataclasses.replace(k, attr=f.name)
    return out


def with_defaults(cls, rules: Mapping[str, Key]) -> dict[str, Key]:
    """The schema `rules` with each key's default read from dataclass `cls`'s field defaults (for a
    dataclass declared elsewhere, so its defaults stay in one place)."""
    defaults = {f.name: f.default for f in dataclasses.fields(cls)}
    return {name: dataclasses.replace(k, attr=k.attr or name, default=defaults[k.attr or name])
            for name, k in rules.items()}


def reference(table: str, schema: Mapping[str, Key]) -> list[str]:
    """The ``[table]`` of a reference document: one ``key = default  # doc; what it accepts`` line per
    key (a key without a default is shown commented out)."""
    lines = [f"[{table}]"]
    for name, k in schema.items():
        rule = f"{k.doc}; {k.expected()}" if k.doc else k.expected()
        if k.default is None or k.default is REQUIRED:
            lines.append(f"# {name} = ...  # {rule}{'' if k.default is None else ' (required)'}")
        else:
            lines.append(f"{name} = {toml_literal(k.default)}  # {rule}")
    return lines


def toml_literal(v: Any) -> str:
    """`v` (bool, number, string, tuple) written as TOML."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, tuple):
        return "[" + ", ".join(toml_literal(x) for x in v) + "]"
    return repr(v)


class Problems:
    """Every problem found in one document, each tied to its dotted key. `origins` maps a dotted key
    (or a table) to where its value came from when that is not the file (``--set KEY=VALUE``)."""

    def __init__(self, path: str, origins: Mapping[str, str] | None = None):
        self.path = path
        self.origins = dict(origins or {})
        self.items: list[tuple[str, str]] = []

    def source(self, key: str) -> str:
        """Where the value of dotted `key` came from: its (or its table's) origin, else the file."""
        return self._origin(key)[0]

    def _origin(self, key: str) -> tuple[str, str | None]:
        parts = key.split(".")
        for n in range(len(parts), 0, -1):
            if (origin := self.origins.get(".".join(parts[:n]))) is not None:
                return origin, ".".join(parts[:n])
        return self.path, None

    def add(self, key: str, problem: str) -> None:
        """Record that `key` is wrong: `problem` says what was expected (or "unknown key ...")."""
        self.items.append((key, problem))

    def lines(self) -> list[str]:
        """``SOURCE: key: problem`` each (an origin that names the key itself is not repeated)."""
        out = []
        for k, p in self.items:
            origin, given = self._origin(k)
            out.append(f"{origin}: {p}" if given == k or not k else f"{origin}: {k}: {p}")
        return out

    def raise_if_any(self) -> None:
        """One ConfigError listing every problem, in the order found."""
        if self.items:
            raise ConfigError("\n".join(self.lines()))


class Section:
    """One TOML table: reads keys against their schema, recording each problem in `problems` (its own,
    or one shared by a whole document). `done()` reports the keys nobody asked for; a Section with its
    own Problems then raises them all."""

    def __init__(self, path: str | Problems, prefix: str, table: Any):
        self.owns = not isinstance(path, Problems)
        self.problems = Problems(path) if self.owns else path
        self.path, self.prefix = self.problems.path, prefix
        self.known: set[str] = set()
        self.bad: set[str] = set()
        if not isinstance(table, dict):
            self.problems.add(prefix, f"expected a table, got {type_name(table)}")
            self.bad.add("")
            table = {}
        self.t = dict(table)

    @property
    def ok(self) -> bool:
        return not self.bad

    def key(self, k: str) -> str:
        return f"{self.prefix}.{k}" if self.prefix else k

    def fail(self, k: str, expected: str, got: Any = None, show_got: bool = True) -> None:
        """Record that key `k` should have been `expected`."""
        self.problem(k, f"expected {expected}" + (f", got {got!r}" if show_got else ""))

    def problem(self, k: str, text: str) -> None:
        self.bad.add(k)
        self.problems.add(self.key(k), text)

    def has(self, k: str) -> bool:
        self.known.add(k)
        return k in self.t

    def take(self, k: str) -> Any:
        """The raw value of `k` (which must be present), marked as read."""
        self.known.add(k)
        return self.t.pop(k)

    def get(self, k: str, key: Key) -> Any:
        """The checked value of `k`; a problem (recorded) or absence gives `key.default`."""
        self.known.add(k)
        if k not in self.t:
            if key.default is REQUIRED:
                self.problem(k, f"missing (expected {key.expected()})")
                return None
            return key.default
        v, problem = key.check(self.t.pop(k))
        if problem is not None:
            self.problem(k, problem)
            return None if key.default is REQUIRED else key.default
        if key.file is not None:
            return self._path(k, v, key.file, must_exist=True)
        return v

    def read(self, schema: Mapping[str, Key]) -> dict[str, Any]:
        """attribute → checked value for every key of `schema` (defaults for absent or bad ones)."""
        return {key.attr or name: self.get(name, key) for name, key in schema.items()}

    def pop(self, k, default, kind, *, lo=None, hi=None, lo_open=False, choices=None, required=False):
        """One key checked against rules given inline (for keys whose rules depend on other values)."""
        return self.get(k, Key(kind, REQUIRED if required else default, lo=lo, hi=hi, lo_open=lo_open,
                               choices=choices))

    def pop_file(self, k, default=None, *, required=False, must_exist=True, what="file"):
        v = self.get(k, Key(str, REQUIRED if required else default))
        return None if v is None else self._path(k, v, what, must_exist)

    def _path(self, k: str, v: str, what: str, must_exist: bool) -> str | None:
        """`v` as an absolute path: relative to the file's directory, ``~`` expanded."""
        p = os.path.expanduser(v)
        if not os.path.isabs(p) and not p.startswith("/dev/"):
            from_file = not self.path.startswith("<") and self.problems.source(self.key(k)) == self.path
            p = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(self.path)), p)) \
                if from_file else os.path.abspath(p)
        if "\0" in p:
            self.fail(k, "a path without NUL characters", v)
            return None
        if must_exist and not os.path.exists(p):
            self.problem(k, f"{what} {p!r} does not exist")
            return None
        return p

    def done(self) -> None:
        """Report each key left over as unknown, with the closest known key as a suggestion."""
        for k in sorted(self.t):
            close = difflib.get_close_matches(str(k), sorted(self.known), n=1, cutoff=0.6)
            hint = f" (did you mean {self.key(close[0])}?)" if close else ""
            self.problem(k, f"unknown key{hint}")
        self.t.clear()
        if self.owns:
            self.problems.raise_if_any()


def type_name(v) -> str:
    """How an error message names the TOML type of `v`."""
    return {bool: "a boolean", int: "an integer", float: "a number", str: "a string", list: "an array",
            dict: "a table"}.get(type(v), type(v).__name__)


def describe(kind) -> str:
    """How an error message names what a key of Python type `kind` expects."""
    return {bool: "true or false", int: "an integer", float: "a number", str: "a string",
            tuple: "an array"}.get(kind, str(kind))


def read_toml(p: Path) -> dict:
    """The parsed TOML file at `p`; a missing or unreadable file is a ConfigError naming it."""
    name = str(p)
    if not p.exists():
        raise ConfigError(f"{name}: no such configuration file")
    if (problem := input_problem(p)) is not None:
        raise ConfigError(f"{name}: {problem}")
    try:
        with open(p, "rb") as f:
            data = f.read(MAX_TOML_BYTES + 1)
    except OSError as e:
        raise ConfigError(f"{name}: cannot read: {e.strerror or e}") from None
    if len(data) > MAX_TOML_BYTES:
        raise ConfigError(f"{name}: over {MAX_TOML_BYTES // 2**20} MiB; a configuration or camera file "
                          "is a few kB")
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

"""The one checker of YAML the toolkit reads: scenes, training configs, ROS parameter files
and session.yaml.

Every error is one :class:`~evdnerf_ros.errors.InputError` in one style,
``<file>: <key path>: <what is allowed>, got <value>``, e.g.::

    scene.yaml: objects[2].motion.keyframes[0].t_s: expected a number, got 'soon'
    cfg.yaml: lr: must be > 0.0 and <= 1000.0, got 1e+30
    session.yaml: views[3].T_world_cam: must be a 4x4 matrix (a list of 4 rows of 4 numbers)

A key path is built with :class:`Where` (``Where(path) / "views" / 3 / "T_world_cam"``);
the checks take the value and its ``Where`` and return the value normalised (ints / floats),
or raise.  ``number_in`` / ``text_in`` read a key of a mapping (missing -> "is missing; it
is required" when required).  :func:`load_yaml` reads a file (UTF-8, size cap) and parses
it with errors naming the file and the line.

This module imports only ``errors`` and ``limits`` at import time (the file reader of
``io.guard`` is imported when a file is read), so every package can use it.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import NoReturn

from .errors import InputError
from .limits import check_number

#: Integers with more digits than this cannot be any valid value (YAML integers may have any
#: number of digits; a float holds about 1e308).
_HUGE_INT = 10 ** 300

_DECIMAL = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?")


class Where:
    """A file and a key path in it: ``Where(path) / "views" / 3`` names ``<path>: views[3]``."""

    __slots__ = ("source", "key")

    def __init__(self, source, key: str = ""):
        self.source, self.key = str(source), str(key)

    def __truediv__(self, sub) -> "Where":
        if isinstance(sub, int) and not isinstance(sub, bool):
            return Where(self.source, f"{self.key}[{sub}]")
        return Where(self.source, f"{self.key}.{sub}" if self.key else str(sub))

    def at(self, key_path: str) -> "Where":
        """The same file at a key path written out (``objects[2].pose``), relative to this one."""
        if not key_path:
            return self
        if not self.key:
            return Where(self.source, key_path)
        return Where(self.source, f"{self.key}{key_path}" if key_path.startswith("[")
                     else f"{self.key}.{key_path}")

    def __str__(self) -> str:
        return f"{self.source}: {self.key}" if self.key else self.source

    def __repr__(self) -> str:
        return f"Where({self.source!r}, {self.key!r})"

    def error(self, msg: str) -> InputError:
        return InputError(f"{self}: {msg}")

    def fail(self, msg: str) -> NoReturn:
        raise self.error(msg)


# --------------------------------------------------------------------------- helpers
def type_name(value) -> str:
    """How a YAML user calls the type of ``value``."""
    if value is None:
        return "null"
    return {dict: "mapping", list: "list", tuple: "list", str: "string", bool: "boolean",
            int: "number", float: "number"}.get(type(value), type(value).__name__)


def a_type(value) -> str:
    """``a list``, ``a mapping``, ``nothing`` (for a missing / null value)."""
    if value is None:
        return "nothing"
    name = type_name(value)
    return f"{'an' if name[0] in 'aeiou' else 'a'} {name}"


def show(value, limit: int = 60) -> str:
    """repr for a message, cut short (a file may hold a huge list by mistake)."""
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 5] + " ...]"


def is_number(value) -> bool:
    """A YAML number a float can hold (not a boolean, not a 300-digit integer)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and not (
        isinstance(value, int) and abs(value) > _HUGE_INT)


# --------------------------------------------------------------------------- values
def mapping(value, where: Where, *, allowed=None, required=(), what: str | None = None,
            optional: bool = False) -> dict | None:
    """A mapping with only ``allowed`` keys (None: any) and every ``required`` one.
    ``optional``: None passes (returns None).  ``what`` describes it in the type error."""
    if value is None and optional:
        return None
    if not isinstance(value, dict):
        desc = what or ("a mapping (key: value lines)" if allowed is None
                        else f"a mapping with keys {', '.join(map(str, allowed))}")
        where.fail(f"must be {desc}, got {a_type(value)}")
    if allowed is not None:
        for k in value:
            if k not in allowed:
                (where / str(k)).fail(f"unknown key {show(k)}; allowed keys here: "
                                      f"{', '.join(map(str, allowed))}")
    for k in required:
        if k not in value:
            where.fail(f"missing required key {k!r}")
    return value


def sequence(value, where: Where, *, min_len: int = 0, max_len: int | None = None,
             what: str = "a list") -> list:
    """A list of ``min_len`` .. ``max_len`` entries."""
    if not isinstance(value, list):
        where.fail(f"must be {what}, got {a_type(value)}")
    if len(value) < min_len:
        where.fail(f"needs at least {min_len} entr{'y' if min_len == 1 else 'ies'}, got {len(value)}")
    if max_len is not None and len(value) > max_len:
        where.fail(f"holds at most {max_len} entr{'y' if max_len == 1 else 'ies'}, got {len(value)}")
    return value


def number(value, where: Where, *, low=None, high=None, low_open: bool = False,
           high_open: bool = False, integer: bool = False, allow_none: bool = False,
           text_numbers: bool = False):
    """A finite number in its range, as int (``integer``) or as written.

    ``text_numbers``: a plain decimal written as text (PyYAML 1.1 reads ``1e-3`` as a
    string) counts as that number; otherwise such text is refused with that hint."""
    if value is None and allow_none:
        return None
    if isinstance(value, str):
        plain = _DECIMAL.fullmatch(value.strip()) is not None
        if plain and text_numbers:
            value = float(value) if any(c in value for c in ".eE") else int(value)
        elif plain:
            where.fail(f"expected a number, got the text {value!r} (YAML reads exponents without "
                       "a dot as text: write 0.001 or 1.0e-3)")
    if isinstance(value, (str, bytes, list, tuple, dict)) or value is None:
        where.fail(f"expected a number, got {show(value)}")
    # the range first, so 1e30 for a count is shown as written; then whole numbers
    value = check_number(value, str(where), low=low, high=high, low_open=low_open)
    if integer:
        value = check_number(value, str(where), integer=True)
    if high_open and high is not None and value >= high:
        lo = "" if low is None else (f"> {low} and " if low_open else f">= {low} and ")
        where.fail(f"must be {lo}< {high}, got {value!r}")
    if integer:
        return int(value)
    return float(value) if not isinstance(value, int) else value


def boolean(value, where: Where) -> bool:
    if not isinstance(value, bool):
        where.fail(f"expected true or false, got {show(value)}")
    return value


def choice(value, where: Where, choices) -> str:
    if not isinstance(value, str) or value not in choices:
        where.fail(f"expected one of {', '.join(map(str, choices))}, got {show(value)}")
    return value


def text(value, where: Where, *, allow_empty: bool = False) -> str:
    if not isinstance(value, str) or (not value and not allow_empty):
        where.fail(f"must be a{'' if allow_empty else ' non-empty'} string, got {show(value)}")
    return value


def vector(value, where: Where, n: int = 3, **limits) -> list:
    """A list of ``n`` numbers, each checked with ``limits`` (as :func:`number`)."""
    if not isinstance(value, list) or len(value) != n:
        where.fail(f"expected a list of {n} numbers, got {show(value)}")
    return [number(x, where / i, **limits) for i, x in enumerate(value)]


def matrix(value, shape, where: Where, *, max_abs: float = 1e12):
    """A ``rows x cols`` matrix of finite numbers of magnitude <= max_abs, as float64."""
    import numpy as np

    rows, cols = shape
    ok = isinstance(value, list) and len(value) == rows and all(
        isinstance(row, list) and len(row) == cols for row in value)
    if not ok:
        where.fail(f"must be a {rows}x{cols} matrix (a list of {rows} rows of {cols} numbers)")
    for i, row in enumerate(value):
        for j, v in enumerate(row):
            if not is_number(v):
                where.fail(f"entry [{i}][{j}] must be a number of plausible size, got {str(v)[:40]}")
    m = np.asarray(value, np.float64)
    if not np.all(np.isfinite(m)):
        where.fail("contains NaN or inf (or a number too large for a float)")
    if m.size and np.abs(m).max() > max_abs:
        where.fail(f"holds entries of magnitude {np.abs(m).max():.3g}; not plausible here "
                   f"(at most {max_abs:g})")
    return m


# --------------------------------------------------------------------------- keys of a mapping
def number_in(sec: dict, key: str, where: Where, *, required: bool = True, **limits):
    """``sec[key]`` checked by :func:`number`; None when absent and not ``required``."""
    value = sec.get(key)
    if value is None:
        if required:
            (where / key).fail("is missing; it is required")
        return None
    return number(value, where / key, **limits)


def text_in(sec: dict, key: str, where: Where, *, required: bool = False, default=None) -> str | None:
    """``sec[key]`` (or ``default``) as a non-empty string; None when absent and not ``required``."""
    value = sec.get(key)
    value = default if value is None else value
    if value is None:
        if required:
            (where / key).fail("is missing; it is required")
        return None
    return text(value, where / key)


# --------------------------------------------------------------------------- files
def parse_yaml(text_: str, source, *, what: str = "YAML file"):
    """Parse YAML text; errors name ``source`` and the line."""
    import yaml

    try:
        return yaml.safe_load(text_)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f" line {mark.line + 1}:" if mark is not None else ""
        problem = getattr(exc, "problem", None) or " ".join(str(exc).split())
        raise InputError(f"{source}:{line} not valid YAML ({problem}); fix the {what}") from None
    except RecursionError:
        raise InputError(f"{source}: YAML nested too deeply to be a {what}") from None
    except (ValueError, OverflowError) as exc:   # e.g. a timestamp PyYAML cannot represent
        raise InputError(f"{source}: not a usable YAML document ({exc})") from None


def load_yaml(path, *, what: str = "YAML file", max_bytes: int | None = None,
              empty: str | None = None):
    """Read ``path`` as UTF-8 (at most ``max_bytes``) and parse it.  ``empty``: if given, an
    empty document is an error ending with this hint; else it is returned as None."""
    from .io.guard import MAX_TEXT_BYTES, read_text

    path = Path(path)
    data = parse_yaml(read_text(path, what=what, max_bytes=max_bytes or MAX_TEXT_BYTES), path,
                      what=what)
    if data is None and empty is not None:
        raise InputError(f"{path}: empty; {empty}")
    return data


__all__ = ["Where", "a_type", "boolean", "choice", "is_number", "load_yaml", "mapping", "matrix",
           "number", "number_in", "parse_yaml", "sequence", "show", "text", "text_in", "type_name",
           "vector"]

"""Prophesee ``.bias`` files: read, check and write.

Format (what Metavision / OpenEB's ``metavision_viewer -b`` read and write): one bias per
line, ``<value> % <name>``, e.g. ``-10   % bias_diff_off``.  Lines that start with ``%``
(header / comment lines such as ``% gen 3.1 CD standard biases``), lines starting with ``#``
and blank lines are skipped; anything after a second ``%`` on a line (older files append
``% v`` / ``% i``) is ignored.  Values are decimal integers (a ``0x`` hexadecimal value is
accepted too), negative allowed: for the IMX636 (EVK4) they are offsets from the sensor's
factory default, as OpenEB's ``Imx636_LL_Biases`` uses them.

Errors name the file and the line and say what would fix it (``BiasFileError``, both a
CameraError and an InputError, so the CLI prints it on one line).
"""

from __future__ import annotations

import os
import re
import tempfile
import warnings
from pathlib import Path
from typing import Mapping

from evdnerf_ros.errors import InputError, OutputExistsError

from .errors import CameraError

__all__ = ["BiasFileError", "BiasRange", "check_biases", "format_biases", "parse_biases",
           "read_bias_file", "write_bias_file"]

_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_INT = re.compile(r"^[+-]?(0[xX][0-9a-fA-F]+|[0-9]+)$")


class BiasFileError(CameraError, InputError):
    """A .bias file (or a bias dict) that cannot be used: syntax, unknown name, range."""


class BiasRange(tuple):
    """(allowed_min, allowed_max, recommended_min, recommended_max) of one bias (inclusive)."""

    def __new__(cls, lo: int, hi: int, rec_lo: int | None = None, rec_hi: int | None = None):
        rec_lo = lo if rec_lo is None else rec_lo
        rec_hi = hi if rec_hi is None else rec_hi
        return super().__new__(cls, (int(lo), int(hi), int(rec_lo), int(rec_hi)))

    lo = property(lambda self: self[0])
    hi = property(lambda self: self[1])
    rec_lo = property(lambda self: self[2])
    rec_hi = property(lambda self: self[3])


def parse_biases(text: str, source: str = "<bias text>") -> dict[str, int]:
    """Parse the text of a .bias file into {name: value} (file order kept)."""
    out: dict[str, int] = {}
    first_line: dict[str, int] = {}
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith("%") or line.startswith("#"):
            continue
        where = f"{source}:{lineno}"
        if "%" not in line:
            raise BiasFileError(f"{where}: expected '<value> % <bias name>', got {raw.strip()!r}; "
                                "write one bias per line, e.g. '0 % bias_diff_on'")
        value_s, rest = line.split("%", 1)
        value_s = value_s.strip()
        name = rest.split("%", 1)[0].strip()
        if not _INT.match(value_s):
            raise BiasFileError(f"{where}: bias value {value_s!r} is not an integer; write a "
                                f"whole number before the '%', e.g. '0 % {name or 'bias_fo'}'")
        if not name or not _NAME.match(name):
            raise BiasFileError(f"{where}: missing or malformed bias name {name!r} after the '%'; "
                                "write e.g. '0 % bias_diff_on'")
        if name in out:
            raise BiasFileError(f"{where}: bias {name} is set twice (first on line "
                                f"{first_line[name]}); keep one line per bias")
        out[name] = int(value_s, 0) if "x" in value_s.lower() else int(value_s, 10)
        first_line[name] = lineno
    return out


def read_bias_file(path, *, ranges: Mapping[str, BiasRange] | None = None) -> dict[str, int]:
    """Read a .bias file; with ``ranges`` also check names and allowed ranges."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise BiasFileError(f"{p}: bias file not found; check the path") from None
    except IsADirectoryError:
        raise BiasFileError(f"{p}: is a directory, not a .bias file; pass the file") from None
    except OSError as exc:
        raise BiasFileError(f"{p}: cannot read the bias file ({exc.strerror or exc}); check "
                            "its permissions") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise BiasFileError(f"{p}: byte {exc.start} is not UTF-8 text; a .bias file is plain "
                            "text lines '<value> % <bias name>'") from None
    biases = parse_biases(text, str(p))
    if not biases:
        raise BiasFileError(f"{p}: no bias lines found; a .bias file holds lines like "
                            "'0 % bias_diff_on'")
    if ranges is not None:
        check_biases(biases, ranges, source=str(p), lines=_line_numbers(text))
    return biases


def _line_numbers(text: str) -> dict[str, int]:
    out = {}
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if line and not line.startswith(("%", "#")) and "%" in line:
            out.setdefault(line.split("%", 1)[1].split("%", 1)[0].strip(), lineno)
    return out


def check_biases(biases: Mapping[str, int], ranges: Mapping[str, BiasRange], *,
                 source: str = "biases", lines: Mapping[str, int] | None = None,
                 warn_recommended: bool = True) -> dict[str, int]:
    """Check names and allowed ranges; returns a plain {name: int} copy.

    Unknown names and values outside the allowed range raise BiasFileError (listing the
    valid names / the range); values outside the recommended range only warn (as OpenEB
    does)."""
    lines = lines or {}
    out: dict[str, int] = {}
    for name, value in biases.items():
        where = f"{source}:{lines[name]}" if name in lines else source
        if name not in ranges:
            raise BiasFileError(f"{where}: unknown bias {name!r}; valid biases: "
                                f"{', '.join(sorted(ranges))}")
        if isinstance(value, bool) or not isinstance(value, (int,)) and not _is_integral(value):
            raise BiasFileError(f"{where}: bias {name} = {value!r} is not an integer; give a "
                                "whole number")
        v = int(value)
        r = ranges[name]
        if not r.lo <= v <= r.hi:
            raise BiasFileError(f"{where}: bias {name} = {v} is outside its allowed range "
                                f"[{r.lo}, {r.hi}]; choose a value in that range")
        if warn_recommended and not r.rec_lo <= v <= r.rec_hi:
            warnings.warn(f"{where}: bias {name} = {v} is outside the recommended range "
                          f"[{r.rec_lo}, {r.rec_hi}]", stacklevel=2)
        out[name] = v
    return out


def _is_integral(value) -> bool:
    try:
        import numpy as np
        return isinstance(value, np.integer)
    except ImportError:  # pragma: no cover
        return False


def format_biases(biases: Mapping[str, int], header: str | None = None) -> str:
    """The text of a .bias file (``%`` header lines first, then ``<value> % <name>``)."""
    lines = []
    if header:
        lines += [f"% {h}".rstrip() for h in str(header).splitlines()]
    for name, value in biases.items():
        if not _NAME.match(str(name)):
            raise BiasFileError(f"bias name {name!r} cannot be written to a .bias file; use "
                                "letters, digits and '_'")
        if isinstance(value, bool) or not (isinstance(value, int) or _is_integral(value)):
            raise BiasFileError(f"bias {name} = {value!r} is not an integer")
        lines.append(f"{int(value):<6d}% {name}")
    return "\n".join(lines) + "\n"


def write_bias_file(path, biases: Mapping[str, int], *, header: str | None = None,
                    overwrite: bool = False) -> Path:
    """Write a .bias file atomically (temp file + rename); refuses to replace an existing
    file unless ``overwrite``."""
    p = Path(path)
    text = format_biases(biases, header)
    if p.exists() and not overwrite:
        raise OutputExistsError(p)
    if not p.parent.is_dir():
        raise BiasFileError(f"{p}: folder {p.parent} does not exist; create it first")
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, p)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return p

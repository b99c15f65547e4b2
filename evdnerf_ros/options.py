"""Job options: each default exists once, in the job's options dataclass.

A job (simulate, sync, convert, eval, ...) declares its knobs as dataclass fields made with
``option(default, help, ...)``.  From that one declaration come

* its command-line flags (``add_options``: ``--field-name``, the range and default in ``--help``),
* its YAML config file (``--config FILE``: keys are the field names, ``-`` or ``_``),
* the values a library caller gets when passing nothing (``Options()``),

and ``options_from_args`` merges them: dataclass defaults < config file < flags typed.  Every
value is checked the same way whichever way it came in: numbers finite and in range
(``limits.check_number``), choices from the list, durations typed as text (``10ms``, ``1.5s``, a bare number
being seconds as everywhere: ``units.parse_duration_ns``) or given as whole ns (the field's unit).  A bad value names the file and key or the flag.
"""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import MISSING, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import InputError
from .limits import check_number

#: argparse stores a flag only when it is typed, so config-file values are not shadowed.
_UNSET = argparse.SUPPRESS


@dataclass(frozen=True)
class OptionSpec:
    """How one options field is typed, checked and shown."""

    help: str
    kind: type | None = None          # int / float / str / bool; None: from the default's type
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    choices: tuple | None = None
    duration: bool = False            # int ns; text "10ms" / "1.5s" is parsed
    nargs: int | None = None          # fixed-length tuples (e.g. a resolution W H)
    metavar: str | tuple | None = None
    flag: str | None = None           # default: "--" + name with dashes
    cli: bool = True                  # False: config file / library only
    none_help: str | None = None      # what None (the default) means, for --help


def option(default=MISSING, help: str = "", *, default_factory=MISSING, **spec) -> Any:
    """A dataclass field carrying its OptionSpec."""
    meta = {"option": OptionSpec(help=help, **spec)}
    if default_factory is not MISSING:
        return field(default_factory=default_factory, metadata=meta)
    return field(default=default, metadata=meta)


def option_fields(cls) -> list[tuple[dataclasses.Field, OptionSpec]]:
    return [(f, f.metadata["option"]) for f in dataclasses.fields(cls) if "option" in f.metadata]


def _default(f: dataclasses.Field):
    return f.default_factory() if f.default is MISSING else f.default


def _kind(f: dataclasses.Field, spec: OptionSpec) -> type:
    if spec.kind is not None:
        return spec.kind
    d = _default(f)
    if isinstance(d, bool):
        return bool
    if isinstance(d, (tuple, list)) and d:
        return type(d[0])
    return type(d) if d is not None else str


def flag_name(f: dataclasses.Field, spec: OptionSpec) -> str:
    return spec.flag or "--" + f.name.replace("_", "-")


def _short_ns(ns: int) -> str:
    for unit, scale in (("s", 10**9), ("ms", 10**6), ("us", 10**3)):
        if ns and ns % scale == 0:
            return f"{ns // scale}{unit}"
    return f"{ns}ns"


def _number_text(v, spec: OptionSpec, kind) -> str:
    if spec.duration:
        return _short_ns(int(v))
    if kind is int and float(v).is_integer():
        return str(int(v))
    return f"{v:g}"


def _show_default(f, spec) -> str:
    d = _default(f)
    if d is None:
        return spec.none_help or "none"
    if isinstance(d, (tuple, list)):
        return " ".join(str(v) for v in d)
    if isinstance(d, (int, float)) and not isinstance(d, bool):
        return _number_text(d, spec, _kind(f, spec))
    return str(d)


def _range_text(f, spec: OptionSpec) -> str:
    if spec.low is None and spec.high is None:
        return ""
    kind = _kind(f, spec)
    lo = None if spec.low is None else _number_text(spec.low, spec, kind)
    hi = None if spec.high is None else _number_text(spec.high, spec, kind)
    if lo is not None and hi is not None:
        return f"in {'(' if spec.low_open else '['}{lo}, {hi}]"
    return f">{'' if spec.low_open else '='} {lo}" if hi is None else f"<= {hi}"


def check_value(value, f: dataclasses.Field, spec: OptionSpec, where: str):
    """One value of field f, from a flag or a config file, checked and converted; InputError names
    `where` (the flag, or 'FILE: key')."""
    if value is None:
        if _default(f) is None:
            return None
        raise InputError(f"{where}: needs a value (default {_show_default(f, spec)})")
    kind = _kind(f, spec)
    if spec.nargs is not None:
        if not isinstance(value, (list, tuple)) or len(value) != spec.nargs:
            raise InputError(f"{where}: expected {spec.nargs} values, got {value!r}")
        names = spec.metavar if isinstance(spec.metavar, tuple) else range(spec.nargs)
        return tuple(_check_one(v, kind, spec, f"{where} {name}") for v, name in zip(value, names))
    return _check_one(value, kind, spec, where)


def _check_one(value, kind, spec: OptionSpec, where: str):
    if spec.duration:
        from .units import parse_duration_ns
        if isinstance(value, str):
            value = parse_duration_ns(value, name=where)
        elif isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise InputError(f"{where}: expected a duration such as 10ms or 1s (or whole ns), got {value!r}")
        return check_number(value, where, low=spec.low, high=spec.high, low_open=spec.low_open)
    if kind is bool:
        if not isinstance(value, bool):
            raise InputError(f"{where}: expected true or false, got {value!r}")
        return value
    if kind in (int, float):
        if isinstance(value, str):
            try:
                value = kind(value)
            except ValueError:
                raise InputError(f"{where}: expected {'a whole number' if kind is int else 'a number'}, "
                                 f"got {value!r}") from None
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        value = check_number(value, where, low=spec.low, high=spec.high, low_open=spec.low_open,
                             integer=kind is int)
    elif kind is str:
        if not isinstance(value, str):
            raise InputError(f"{where}: expected text, got {value!r}")
    if spec.choices is not None and value not in spec.choices:
        raise InputError(f"{where}: {value!r} is not one of {', '.join(map(str, spec.choices))}")
    return value


def _argparse_type(f, spec: OptionSpec, flag: str):
    kind = _kind(f, spec)

    def parse(text):
        try:
            return _check_one(text, str if spec.duration else kind, spec, flag)
        except InputError as exc:
            raise argparse.ArgumentTypeError(str(exc).removeprefix(f"{flag}: ")) from None

    parse.__name__ = "duration" if spec.duration else kind.__name__
    return parse


def add_options(parser: argparse.ArgumentParser, cls, *, exclude=(), config: bool = True) -> None:
    """Flags for every CLI field of the options dataclass `cls` (and --config FILE)."""
    if config:
        parser.add_argument("--config", metavar="FILE", default=_UNSET,
                            help="YAML file of option values (keys: the flags' or the options' names); flags typed win")
    for f, spec in option_fields(cls):
        if not spec.cli or f.name in exclude:
            continue
        flag = flag_name(f, spec)
        kind = _kind(f, spec)
        if kind is bool and spec.nargs is None:
            on = not _default(f)
            name = flag if on else "--no-" + flag.removeprefix("--")
            action = parser.add_argument(name, dest=f.name, action="store_true" if on else "store_false",
                                         default=_UNSET, help=spec.help)
            action.option = (spec.help, "", "")
            continue
        text = spec.help
        rng = _range_text(f, spec)
        extra = ", ".join(x for x in (rng, f"default {_show_default(f, spec)}") if x)
        # several values: checked together by options_from_args, so the message names which one
        typ = str if spec.nargs is not None else _argparse_type(f, spec, flag)
        action = parser.add_argument(flag, dest=f.name, type=typ, default=_UNSET,
                                     nargs=spec.nargs,
                                     metavar=spec.metavar or _choices_metavar(spec) or flag.removeprefix("--").upper(),
                                     help=f"{text} ({extra})".replace("%", "%%"))
        # (help, range or choices, default) apart, for the generated reference (docs/make_reference.py)
        action.option = (text, rng or (", ".join(map(str, spec.choices)) if spec.choices else ""),
                         _show_default(f, spec))


def _choices_metavar(spec: OptionSpec):
    return "{" + ",".join(map(str, spec.choices)) + "}" if spec.choices else None


def load_config(path, cls) -> dict:
    """The values of a YAML config file for `cls`, checked: unknown keys and bad values name the
    file and key."""
    from .yamlcheck import load_yaml

    data = load_yaml(path, what="config file")
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a mapping of option: value, got {type(data).__name__}")
    known = {f.name: (f, spec) for f, spec in option_fields(cls)}
    known.update({flag_name(f, spec).removeprefix("--").replace("-", "_"): (f, spec)
                  for f, spec in option_fields(cls) if spec.cli})
    values = {}
    for key, value in data.items():
        name = str(key).replace("-", "_")
        if name not in known:
            raise InputError(f"{path}: {key}: unknown option; allowed: {', '.join(sorted(known))}")
        f, spec = known[name]
        values[f.name] = check_value(value, f, spec, f"{path}: {key}")
    return values


def options_from_args(cls, args: argparse.Namespace, *, exclude=(), **fixed):
    """cls from its defaults, then --config FILE, then the flags typed, then `fixed` (values the
    command computes itself)."""
    values = {}
    config = getattr(args, "config", None)
    if config:
        values.update({k: v for k, v in load_config(Path(config), cls).items() if k not in exclude})
    for f, spec in option_fields(cls):
        if f.name in exclude or not hasattr(args, f.name):
            continue
        value = getattr(args, f.name)
        values[f.name] = check_value(value, f, spec, flag_name(f, spec)) if spec.nargs else value
    values.update(fixed)
    return cls(**values)

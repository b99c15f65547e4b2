"""The ``--ros-args`` that ``ros2 run`` / ``ros2 launch`` pass to an executable.

Supported (rcl's syntax): ``-p|--param name:=value`` (value parsed as YAML),
``--params-file FILE``, ``-r|--remap [node:]from:=to`` including ``__node:=`` /
``__name:=`` and ``__ns:=``, ``--log-level [name:=]LEVEL``. ``--ros-args`` may appear
several times; a lone ``--`` ends it. Flags rcl knows that have no meaning here
(``--enclave``, ``--log-config-file``, ``--[disable-|enable-]rosout-logs``,
``--[disable-|enable-]stdout-logs``, ``--[disable-|enable-]external-lib-logs``) are
accepted and ignored; anything else inside ``--ros-args`` is an error.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import yaml

from ..errors import InputError

LOG_LEVELS = ("debug", "info", "warn", "error", "fatal")
_IGNORED_WITH_VALUE = {"-e", "--enclave", "--log-config-file"}
_IGNORED_FLAGS = {f"--{p}{k}-logs" for p in ("disable-", "enable-") for k in ("rosout", "stdout", "external-lib")}


@dataclass
class RosArgs:
    params: dict[str, object] = field(default_factory=dict)   # -p overrides, in order
    params_files: list[Path] = field(default_factory=list)
    remaps: dict[str, str] = field(default_factory=dict)      # topic remaps for this node
    node_name: str | None = None
    namespace: str | None = None
    log_level: str | None = None


def _split_assign(text: str, flag: str) -> tuple[str, str]:
    if ":=" not in text:
        raise InputError(f"--ros-args {flag} {text!r}: expected 'name:=value'")
    name, value = text.split(":=", 1)
    if not name:
        raise InputError(f"--ros-args {flag} {text!r}: empty name before ':='")
    return name, value


def parse_value(text: str, what: str):
    """A parameter value as rcl reads it: YAML (``true``, ``3``, ``0.5``, ``[1, 2]``, ``'txt'``)."""
    try:
        return yaml.safe_load(text) if text != "" else ""
    except yaml.YAMLError as exc:
        raise InputError(f"{what}: value {text!r} is not valid YAML ({exc.__class__.__name__}); quote strings "
                         "that contain ':' or brackets") from None


def split_ros_args(argv: list[str]) -> tuple[list[str], list[str]]:
    """(non-ROS arguments, the tokens inside every ``--ros-args`` block)."""
    user, ros = [], []
    inside = False
    for tok in argv:
        if tok == "--ros-args":
            inside = True
        elif inside and tok == "--":
            inside = False
        elif inside:
            ros.append(tok)
        else:
            user.append(tok)
    return user, ros


def parse_ros_args(argv: list[str], node_name: str) -> tuple[RosArgs, list[str]]:
    """Parse ``argv`` (without the program name) for the node `node_name` -> (RosArgs, other args)."""
    user, toks = split_ros_args(list(argv))
    out = RosArgs()
    i = 0

    def value(flag):
        nonlocal i
        if i + 1 >= len(toks):
            raise InputError(f"--ros-args {flag}: missing its argument")
        i += 1
        return toks[i]

    while i < len(toks):
        tok = toks[i]
        if tok in ("-p", "--param"):
            name, val = _split_assign(value(tok), tok)
            if ":" in name:               # node-specific: node:name:=value
                target, name = name.split(":", 1)
                if target != node_name:
                    i += 1
                    continue
            out.params[name] = parse_value(val, f"--ros-args {tok} {name}")
        elif tok == "--params-file":
            path = Path(value(tok))
            if not path.is_file():
                raise InputError(f"--ros-args --params-file {path}: no such file")
            out.params_files.append(path)
        elif tok in ("-r", "--remap"):
            src, dst = _split_assign(value(tok), tok)
            if ":" in src and not src.startswith("~"):
                target, src = src.split(":", 1)
                if target != node_name:
                    i += 1
                    continue
            if src in ("__node", "__name"):
                out.node_name = dst
            elif src == "__ns":
                out.namespace = dst
            else:
                out.remaps[src] = dst
        elif tok == "--log-level":
            lvl = value(tok)
            if ":=" in lvl:
                logger, lvl = _split_assign(lvl, tok)
                if logger != node_name:
                    i += 1
                    continue
            if lvl.lower() not in LOG_LEVELS:
                raise InputError(f"--ros-args --log-level {lvl!r}: expected one of {list(LOG_LEVELS)}")
            out.log_level = lvl.lower()
        elif tok in _IGNORED_WITH_VALUE:
            value(tok)
        elif tok in _IGNORED_FLAGS:
            pass
        else:
            raise InputError(f"--ros-args: unknown argument {tok!r}; supported: -p name:=value, --params-file FILE, "
                             "-r from:=to (and __node:=, __ns:=), --log-level LEVEL")
        i += 1
    return out, user

"""Typed, declared node parameters and ``ros__parameters`` YAML files.

A node declares every parameter (:class:`ParameterSpec`: name, default, description, and
optionally read-only, a numeric range or a set of choices). Values come, in increasing
precedence, from the defaults, each ``--params-file`` in order, then ``-p`` overrides.
A parameter file maps node names to ``{ros__parameters: {...}}``; the keys that apply to
node ``/ns/name`` are ``/**``, ``**``, ``/**/name``, ``name``, ``/name`` (when ns is ``/``),
``ns/name`` and ``/ns/name``, applied in the file's order. Nested mappings are flattened
with ``.`` (``camera: {width: 64}`` sets ``camera.width``). Values set for a parameter
this node does not declare are reported (a typo would otherwise go unnoticed), not used.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from ..errors import InputError
from ..yamlcheck import Where, load_yaml, mapping

_TYPES = (bool, int, float, str, list)


@dataclass(frozen=True)
class ParameterSpec:
    name: str
    default: Any
    description: str
    type: type | None = None         # default: type(default); list means list of numbers/strings
    read_only: bool = False          # only settable at start-up (files, -p), as ROS read_only
    dynamic: bool = False            # may change while the node runs (ros2 param set) and takes effect live
    min: float | None = None
    max: float | None = None
    choices: tuple | None = None

    @property
    def kind(self) -> type:
        return self.type or type(self.default)

    @property
    def ros_type(self) -> int:
        """rcl_interfaces/msg/ParameterType of this parameter (lists: double or string arrays)."""
        kind = self.kind
        if kind is list:
            return 9 if any(isinstance(v, str) for v in self.default) else 8
        return {bool: 1, int: 2, float: 3, str: 4}[kind]

    def type_name(self) -> str:
        return {bool: "bool", int: "integer", float: "double", str: "string", list: "array"}[self.kind]

    def coerce(self, value, source: str):
        kind = self.kind
        what = f"{source}: parameter {self.name!r}"
        ok = True
        if kind is bool:
            ok = isinstance(value, bool)
        elif kind is int:
            ok = isinstance(value, int) and not isinstance(value, bool)
        elif kind is float:
            ok = isinstance(value, (int, float)) and not isinstance(value, bool)
            value = float(value) if ok else value
        elif kind is str:
            if isinstance(value, bool) and self.choices is not None and str(value).lower() in self.choices:
                value = str(value).lower()       # `-p name:=false` reads as a bool: that choice
            ok = isinstance(value, str)
        elif kind is list:
            ok = isinstance(value, (list, tuple))
            value = list(value) if ok else value
        if not ok:
            raise InputError(f"{what} is a {self.type_name()}, got {type(value).__name__} {value!r}; "
                             f"e.g. {self.name}:={_example(self.default)}")
        if self.choices is not None and value not in self.choices:
            raise InputError(f"{what}: {value!r} is not one of {list(self.choices)}")
        if (self.min is not None and value < self.min) or (self.max is not None and value > self.max):
            raise InputError(f"{what}: {value!r} is outside its range [{self.min}, {self.max}]")
        return value


def _example(default) -> str:
    return yaml.safe_dump(default, default_flow_style=True).strip().removesuffix("...").strip()


def _flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


def _applies(key: str, node: str, namespace: str) -> bool:
    key = str(key)
    ns = namespace.strip("/")
    full = f"{ns}/{node}" if ns else node
    return key in ("/**", "**", f"/**/{node}", f"**/{node}", full, "/" + full) or (not ns and key == node)


def load_params_file(path, node: str, namespace: str = "/") -> dict[str, Any]:
    """The flattened ``ros__parameters`` a file gives node `node` in `namespace`; the file's
    structure is checked with ``evdnerf_ros.yamlcheck`` (errors name the file and the key)."""
    path = Path(path)
    data = load_yaml(path, what="parameter file")
    if data is None:
        return {}
    top = Where(path)
    mapping(data, top, what="a mapping of node names to {ros__parameters: ...}")
    out: dict[str, Any] = {}
    for key, body in data.items():
        where = top / str(key)
        if not isinstance(body, dict) or "ros__parameters" not in body:
            where.fail(f"has no 'ros__parameters' mapping; write "
                       f"'{key}:\\n  ros__parameters:\\n    name: value'")
        params = mapping(body["ros__parameters"], where / "ros__parameters",
                         what="a mapping of parameter names to values")
        if _applies(key, node, namespace):
            out.update(_flatten(params))
    return out


class Parameters:
    """Declared parameters with their current values (``params["name"]`` or ``params.name``)."""

    def __init__(self, specs):
        import threading

        self._specs: dict[str, ParameterSpec] = {}
        self._values: dict[str, Any] = {}
        self._sources: dict[str, str] = {}
        self._lock = threading.RLock()
        #: callables(changes: dict) -> None or a reason to refuse the whole set (run before applying)
        self.validators: list = []
        #: callables(changes: dict) called after a run-time set was applied (in the setter's thread)
        self.listeners: list = []
        for s in specs:
            self.declare(s)

    def check_runtime(self, name: str, value, source: str):
        """The value `name` would take from a run-time set; raises InputError with the reason."""
        spec = self._specs.get(name)
        if spec is None:
            raise InputError(f"parameter {name!r} is not declared by this node")
        if spec.read_only or not spec.dynamic:
            raise InputError(f"parameter {name!r} is read-only while the node runs; set it at start-up "
                             f"(--ros-args -p {name}:=VALUE or a --params-file)")
        return spec.coerce(value, source)

    def set_runtime(self, values: list[tuple[str, Any]], source: str, *, atomically: bool = False) -> list:
        """Set parameters while the node runs (the parameter services). Returns one reason per
        value (None: applied). ``atomically``: all or none (one reason for all on failure).
        Without it each value is checked and applied on its own, as ROS 2's set_parameters."""
        with self._lock:
            reasons: list = []
            checked: dict[str, Any] = {}
            for name, value in values:
                try:
                    checked[name] = self.check_runtime(name, value, source)
                    reasons.append(None)
                except InputError as exc:
                    reasons.append(str(exc))
            if atomically:
                bad = next((r for r in reasons if r), None)
                if bad is None:
                    bad = self._validate(checked)
                if bad is not None:
                    return [bad] * len(values)
                self._commit(checked, source)
                return reasons
            for i, (name, _) in enumerate(values):
                if reasons[i] is None:
                    one = {name: checked[name]}
                    reasons[i] = self._validate(one)
                    if reasons[i] is None:
                        self._commit(one, source)
            return reasons

    def _validate(self, changes: dict):
        for check in self.validators:
            reason = check(dict(changes))
            if reason:
                return reason
        return None

    def _commit(self, changes: dict, source: str) -> None:
        for name, value in changes.items():
            self._values[name] = value
            self._sources[name] = source
        for listener in list(self.listeners):
            listener(dict(changes))

    def declare(self, spec: ParameterSpec) -> None:
        if spec.name in self._specs:
            raise InputError(f"parameter {spec.name!r} declared twice")
        if spec.kind not in _TYPES:
            raise InputError(f"parameter {spec.name!r}: unsupported type {spec.kind}")
        self._specs[spec.name] = spec
        self._values[spec.name] = spec.coerce(spec.default, "default")
        self._sources[spec.name] = "default"

    def apply(self, values: dict[str, Any], source: str, *, startup: bool = True) -> list[str]:
        """Set values; returns the names this node does not declare (left unused)."""
        unknown = []
        checked = {}
        for name, value in values.items():
            spec = self._specs.get(name)
            if spec is None:
                unknown.append(name)
                continue
            if spec.read_only and not startup:
                raise InputError(f"{source}: parameter {name!r} is read-only after start-up")
            checked[name] = spec.coerce(value, source)
        for name, value in checked.items():     # all or nothing
            self._values[name] = value
            self._sources[name] = source
        return unknown

    def __getitem__(self, name: str):
        try:
            return self._values[name]
        except KeyError:
            raise InputError(f"parameter {name!r} is not declared") from None

    def __getattr__(self, name: str):
        if name.startswith("_"):
            raise AttributeError(name)
        return self[name.replace("__", ".")]

    def specs(self) -> list[ParameterSpec]:
        return list(self._specs.values())

    def source(self, name: str) -> str:
        return self._sources[name]

    def as_dict(self) -> dict[str, Any]:
        return dict(self._values)

    def to_yaml(self, node: str) -> str:
        """A ``ros__parameters`` file of the current values (what ``ros2 param dump`` gives)."""
        return yaml.safe_dump({node: {"ros__parameters": self.as_dict()}}, sort_keys=False)

"""The one YAML checker: "file: key path: what is allowed" for scenes, training configs and
ROS parameter files alike (and the helpers session.yaml's reader can use)."""

from __future__ import annotations

import numpy as np
import pytest

from evdnerf_ros import yamlcheck as yc
from evdnerf_ros.errors import InputError
from evdnerf_ros.yamlcheck import Where


def test_where_names_file_and_key_path():
    w = Where("s.yaml")
    assert str(w) == "s.yaml" and str(w / "views" / 3 / "T_world_cam") == "s.yaml: views[3].T_world_cam"
    assert str(w.at("objects[2].pose") / "position") == "s.yaml: objects[2].pose.position"
    assert str((w / "objects").at("[1]")) == "s.yaml: objects[1]"
    with pytest.raises(InputError, match=r"^s\.yaml: a\.b: went wrong$"):
        (w / "a" / "b").fail("went wrong")


@pytest.mark.parametrize("call, message", [
    (lambda w: yc.mapping([1], w / "cam"), r"^f\.yaml: cam: must be a mapping \(key: value lines\), got a list$"),
    (lambda w: yc.mapping(None, w / "cam"), "cam: must be a mapping .*, got nothing"),
    (lambda w: yc.mapping({"a": 1, "zz": 2}, w / "cam", allowed=("a", "b")),
     r"^f\.yaml: cam\.zz: unknown key 'zz'; allowed keys here: a, b$"),
    (lambda w: yc.mapping({"a": 1}, w, allowed=("a", "b"), required=("b",)), "f.yaml: missing required key 'b'"),
    (lambda w: yc.sequence({}, w / "views", min_len=1), "views: must be a list, got a mapping"),
    (lambda w: yc.sequence([], w / "views", min_len=1), "views: needs at least 1 entry, got 0"),
    (lambda w: yc.number("wide", w / "width"), r"width: expected a number, got 'wide'"),
    (lambda w: yc.number(True, w / "width"), r"width: expected a number, got True"),
    (lambda w: yc.number("1e-3", w / "eps"), r"eps: expected a number, got the text '1e-3' \(YAML reads"),
    (lambda w: yc.number(float("nan"), w / "c"), r"f\.yaml: c: must be a finite number, got nan"),
    (lambda w: yc.number(70000, w / "camera" / "width", low=1, high=65535, integer=True),
     r"^f\.yaml: camera\.width: must be >= 1 and <= 65535, got 70000$"),
    (lambda w: yc.number(2.5, w / "h", low=1, integer=True), r"h: expected a whole number, got 2\.5"),
    (lambda w: yc.number(1.0, w / "fov", low=0, high=1.0, low_open=True, high_open=True),
     r"fov: must be > 0 and < 1\.0, got 1\.0"),
    (lambda w: yc.number(10 ** 400, w / "c"), "c: a 401-digit number is outside any valid range"),
    (lambda w: yc.boolean("maybe", w / "on"), "on: expected true or false, got 'maybe'"),
    (lambda w: yc.choice("cone", w / "type", ("box", "sphere")), "type: expected one of box, sphere, got 'cone'"),
    (lambda w: yc.text("", w / "name"), "name: must be a non-empty string, got ''"),
    (lambda w: yc.vector([1, 2], w / "xyz"), r"xyz: expected a list of 3 numbers, got \[1, 2\]"),
    (lambda w: yc.vector([1, "a", 3], w / "xyz"), r"xyz\[1\]: expected a number"),
    (lambda w: yc.matrix([[1, 2], [3, 4]], (3, 3), w / "K"), "K: must be a 3x3 matrix"),
    (lambda w: yc.matrix([["a", 0], [0, 1]], (2, 2), w / "K"), r"K: entry \[0\]\[0\] must be a number"),
    (lambda w: yc.matrix([[np.inf, 0], [0, 1]], (2, 2), w / "K"), "K: contains NaN or inf"),
    (lambda w: yc.number_in({}, "c_pos", w / "thresholds"), r"thresholds\.c_pos: is missing; it is required"),
    (lambda w: yc.text_in({"bag": 3}, "bag", w / "views" / 0), r"views\[0\]\.bag: must be a non-empty string"),
])
def test_every_check_names_file_key_and_what_is_allowed(call, message):
    with pytest.raises(InputError, match=message):
        call(Where("f.yaml"))


def test_checks_return_normalised_values():
    w = Where("f.yaml")
    assert yc.number(3, w, integer=True) == 3 and isinstance(yc.number(3.0, w, integer=True), int)
    assert yc.number("1e-3", w, text_numbers=True) == 0.001 and yc.number(None, w, allow_none=True) is None
    assert yc.vector([1, 2, 3], w) == [1, 2, 3]
    np.testing.assert_array_equal(yc.matrix([[1, 2], [3, 4]], (2, 2), w), [[1.0, 2.0], [3.0, 4.0]])
    assert yc.mapping(None, w, optional=True) is None
    assert yc.number_in({}, "x", w, required=False) is None and yc.text_in({}, "b", w, default="v") == "v"


def test_load_yaml_names_file_and_line(tmp_path):
    p = tmp_path / "p.yaml"
    p.write_text("a: 1\nb: [\n")
    with pytest.raises(InputError, match=rf"^{p}: line 3: not valid YAML \(.*\); fix the parameter file$"):
        yc.load_yaml(p, what="parameter file")
    p.write_text("")
    assert yc.load_yaml(p) is None
    with pytest.raises(InputError, match=f"{p}: empty; say something"):
        yc.load_yaml(p, empty="say something")
    p.write_bytes(b"a: \xff\n")
    with pytest.raises(InputError, match="byte offset 3: byte 0xff on line 1 is not UTF-8"):
        yc.load_yaml(p)
    with pytest.raises(InputError, match="no such scene file"):
        yc.load_yaml(tmp_path / "none.yaml", what="scene file")
    p.write_text("a: " + "[" * 2000 + "]" * 2000 + "\n")
    with pytest.raises(InputError, match="nested too deeply"):
        yc.load_yaml(p)


# ---------------------------------------------------------------- the three readers, one style
SPHERE = "objects:\n  - {type: sphere, radius: 0.3}\n"


@pytest.mark.parametrize("text, message", [
    ("objects:\n  - {type: sphere, radius: 0.3, colour: red}\n",
     r"objects\[0\]\.colour: unknown key 'colour'; allowed keys here: name, type"),
    ("objects:\n  - {type: sphere, radius: big}\n", r"objects\[0\]\.radius: expected a number, got 'big'"),
    ("objects:\n  - {type: sphere, radius: -1}\n", r"objects\[0\]\.radius: must be > 0\.0, got -1"),
    ("cameras: {intrinsics: {width: 20000}}\n" + SPHERE, r"cameras\.intrinsics\.width: must be >= 1 and <= 16384"),
    ("cameras: {ring: {elevation_deg: 89}}\n" + SPHERE, r"cameras\.ring\.elevation_deg: must be > -89\.0 and < 89\.0"),
    ("lights: {shadows: 1}\n" + SPHERE, "lights.shadows: expected true or false, got 1"),
    ("lights: [1]\n" + SPHERE, "lights: must be a mapping with keys ambient, directional, shadows, got a list"),
])
def test_scene_files(tmp_path, text, message):
    from evdnerf_ros.sim.scene import load_scene

    p = tmp_path / "scene.yaml"
    p.write_text(text)
    with pytest.raises(InputError, match=f"^{p}: {message}"):
        load_scene(p, check_cameras=False)


@pytest.mark.parametrize("text, message", [
    ("lrr: 0.1\n", "lrr: unknown key 'lrr'; allowed keys here: backbone"),
    ("rays: many\n", "rays: expected a number, got 'many'"),
    ("rays: 0\n", "rays: must be >= 1 and <= 16777216, got 0"),
    ("field: {features: 0}\n", r"field\.features: must be >= 1 and <= 4096, got 0"),
    ("windows: [4, 0]\nwindow_switch: [0.5]\n", r"windows\[1\]: must be >= 1"),
    ("box: [[0, 0, 0], [1, 1, 1e7]]\n", r"box\[1\]\[2\]: must be >= -1000000\.0 and <= 1000000\.0"),
])
def test_training_configs(tmp_path, text, message):
    from evdnerf_ros.train.config import TrainConfig

    p = tmp_path / "cfg.yaml"
    p.write_text(text)
    with pytest.raises(InputError, match=f"^{p}: {message}"):
        TrainConfig.load(p)


@pytest.mark.parametrize("text, message", [
    ("- 1\n", r"must be a mapping of node names to \{ros__parameters: ...\}, got a list"),
    ("pub:\n  n: 3\n", "pub: has no 'ros__parameters' mapping"),
    ("pub:\n  ros__parameters: [1]\n", "pub.ros__parameters: must be a mapping of parameter names to values, got a list"),
    ("pub:\n  ros__parameters: {a: [\n", "line 3: not valid YAML"),
])
def test_parameter_files(tmp_path, text, message):
    from evdnerf_ros.ros.parameters import load_params_file

    p = tmp_path / "params.yaml"
    p.write_text(text)
    with pytest.raises(InputError, match=f"^{p}: {message}"):
        load_params_file(p, "pub")

"""Launch files are checked statically (launch_ros is not installed here, and launch files are
never executed in tests): every Node(...) in launch/*.launch.py must name package `rig`, an
executable installed as a console script of this distribution, and parameter files that exist,
are installed by setup.py and hold only parameters the node declares."""

import ast
import glob
import importlib
import inspect
from importlib.metadata import distribution
from pathlib import Path

import pytest
import yaml

from evdnerf_ros.ros.node import Node
from evdnerf_ros.ros.parameters import _flatten, load_params_file

ROOT = Path(__file__).resolve().parents[1]


def console_scripts() -> dict[str, str]:
    return {ep.name: ep.value for ep in distribution("rig").entry_points if ep.group == "console_scripts"}


def installed_data_files() -> set[str]:
    """Repository paths setup.py installs as data_files (its glob patterns, evaluated here)."""
    tree = ast.parse((ROOT / "setup.py").read_text())
    out = set()
    for call in ast.walk(tree):
        if isinstance(call, ast.Call) and getattr(call.func, "id", None) == "glob" and call.args:
            out.update(str(Path(p)) for p in glob.glob(str(ROOT / call.args[0].value)))
    return {str(Path(p).relative_to(ROOT)) for p in out}


def declared_parameters(entry: str) -> set[str]:
    module = importlib.import_module(entry.split(":")[0])
    nodes = [c for _, c in inspect.getmembers(module, inspect.isclass) if issubclass(c, Node) and c is not Node
             and c.__module__ == module.__name__]
    return {s.name for c in nodes for s in c.PARAMETERS}


def _resolve(expr, assigned):
    """A launch-file expression as a repository path (str), a dict of parameters, or None."""
    if isinstance(expr, ast.Name) and expr.id in assigned:
        return _resolve(assigned[expr.id], assigned)
    if isinstance(expr, ast.Constant) and isinstance(expr.value, str):
        return expr.value
    if isinstance(expr, ast.Call) and ast.unparse(expr.func) == "os.path.join":
        first, *rest = expr.args
        if not (isinstance(first, ast.Call) and ast.unparse(first.func) == "get_package_share_directory"):
            return None
        if first.args[0].value != "rig":
            return f"<share of {first.args[0].value}>"
        return str(Path(*[a.value for a in rest]))
    if isinstance(expr, (ast.Dict, ast.DictComp)):
        if isinstance(expr, ast.Dict):
            return {k.value: v for k, v in zip(expr.keys, expr.values)}
        gen = expr.generators[0]
        names = _resolve(gen.iter, assigned) if not isinstance(gen.iter, (ast.Tuple, ast.List)) else \
            [e.value for e in gen.iter.elts]
        return {n: None for n in names}
    return None


def check_launch_file(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    assigned = {t.id: node.value for node in ast.walk(tree) if isinstance(node, ast.Assign)
                for t in node.targets if isinstance(t, ast.Name)}
    scripts, data = console_scripts(), installed_data_files()
    problems, nodes = [], 0
    for call in ast.walk(tree):
        if not (isinstance(call, ast.Call) and ast.unparse(call.func).split(".")[-1] == "Node"):
            continue
        nodes += 1
        kw = {k.arg: k.value for k in call.keywords}
        where = f"{path.name}:{call.lineno}"
        pkg, exe = (_resolve(kw.get(k), assigned) for k in ("package", "executable"))
        if pkg != "rig":
            problems.append(f"{where}: package {pkg!r} is not 'rig'")
        if exe not in scripts:
            problems.append(f"{where}: executable {exe!r} is not a console script of rig ({sorted(scripts)})")
            continue
        declared = declared_parameters(scripts[exe])
        name = _resolve(kw.get("name"), assigned) or exe
        params = kw.get("parameters")
        for item in (params.elts if isinstance(params, ast.List) else []):
            value = _resolve(item, assigned)
            if isinstance(value, dict):
                unknown = set(value) - declared
                if unknown:
                    problems.append(f"{where}: parameters {sorted(unknown)} are not declared by {exe}")
            elif isinstance(value, str):
                if value not in data or not (ROOT / value).is_file():
                    problems.append(f"{where}: parameter file {value} does not exist or is not installed by setup.py")
                    continue
                keys = set(load_params_file(ROOT / value, name))
                if not keys:
                    problems.append(f"{where}: {value} has no ros__parameters for node {name!r}")
                if keys - declared:
                    problems.append(f"{where}: {value} sets {sorted(keys - declared)}, not declared by {exe}")
            else:
                problems.append(f"{where}: cannot resolve parameters entry {ast.unparse(item)} statically")
    if not nodes:
        problems.append(f"{path.name}: no Node(...) found")
    return problems


LAUNCH_FILES = sorted((ROOT / "launch").glob("*.launch.py"))


def test_there_are_launch_files_and_they_are_installed():
    assert LAUNCH_FILES, "launch/ has no *.launch.py"
    assert {f"launch/{p.name}" for p in LAUNCH_FILES} <= installed_data_files()
    assert "config/event_publisher.yaml" in installed_data_files()


@pytest.mark.parametrize("path", LAUNCH_FILES, ids=lambda p: p.name)
def test_launch_file_nodes_name_installed_executables_and_parameter_files(path):
    assert check_launch_file(path) == []
    tree = ast.parse(path.read_text())
    assert any(isinstance(n, ast.FunctionDef) and n.name == "generate_launch_description" for n in tree.body)


def test_checker_catches_bad_launch_files(tmp_path):
    bad = tmp_path / "bad.launch.py"
    bad.write_text(
        "from launch_ros.actions import Node\nimport os\n"
        "def generate_launch_description():\n"
        "    p = os.path.join(get_package_share_directory('rig'), 'config', 'missing.yaml')\n"
        "    return LaunchDescription([Node(package='rig', executable='no_such_exe'),\n"
        "        Node(package='rig', executable='event_publisher', parameters=[p, {'not_a_param': 1}])])\n")
    problems = check_launch_file(bad)
    assert any("no_such_exe" in m for m in problems)
    assert any("missing.yaml" in m for m in problems)
    assert any("not_a_param" in m for m in problems)


def test_parameter_yaml_sets_only_declared_parameters():
    keys = set(load_params_file(ROOT / "config/event_publisher.yaml", "event_publisher", "/robot"))
    declared = declared_parameters(console_scripts()["event_publisher"])
    assert keys and keys <= declared
    data = yaml.safe_load((ROOT / "config/event_publisher.yaml").read_text())
    assert keys == set(_flatten(next(iter(data.values()))["ros__parameters"]))

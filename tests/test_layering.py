"""The package layering of evdnerf_ros (docs/architecture.md, "Layout"): imports only go down the ranks below,
so there is no import circle between packages, and only the simulator's users import sim/."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "evdnerf_ros"

#: A module or package may import only what has a lower rank (and itself).
RANK = {
    "errors": 0, "topics": 0, "__version__": 0,
    "units": 1, "limits": 1, "atomic": 1, "renderer": 1, "device": 1, "share": 1,
    "events": 2, "geometry": 2,
    "io": 3,
    "yamlcheck": 4,
    "options": 5,
    "ros": 6, "field": 6, "session": 6,
    "sim": 7, "train": 7, "calib": 7,
    "nodes": 8,
    "eval": 9,                     # eval scores what the publisher node emits (eval.published)
    "demo": 10,
    "cli": 11, "__main__": 12,
}
#: Who may import the simulator: its own commands, the publisher (which simulates a scene) and
#: evaluation (which scores the true scene of a simulated training set as its reference).
SIM_USERS = {"nodes", "demo", "cli", "eval"}


def package_imports() -> dict[str, set[str]]:
    """top-level module / package of evdnerf_ros -> the top-level ones it imports (lazy imports too)."""
    edges: dict[str, set[str]] = {}
    for f in ROOT.rglob("*.py"):
        parts = list(f.relative_to(ROOT).with_suffix("").parts)
        if parts == ["__init__"]:              # the package's own __init__: only __version__
            continue
        src = parts[0]
        if parts[-1] == "__init__":
            parts = parts[:-1]
        package = parts if f.name == "__init__.py" else parts[:-1]
        for node in ast.walk(ast.parse(f.read_text())):
            targets = []
            if isinstance(node, ast.ImportFrom) and node.level:
                base = package[:len(package) - node.level + 1]
                if node.module:
                    targets = [(base + node.module.split("."))[0]]
                else:
                    targets = [base[0]] if base else [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("evdnerf_ros."):
                targets = [node.module.split(".")[1]]
            elif isinstance(node, ast.Import):
                targets = [a.name.split(".")[1] for a in node.names if a.name.startswith("evdnerf_ros.")]
            edges.setdefault(src, set()).update(t for t in targets if t != src)
    return edges


def test_every_package_has_a_rank():
    assert set(package_imports()) <= set(RANK), set(package_imports()) - set(RANK)


def test_imports_only_go_down():
    wrong = [f"{src} -> {dst}" for src, dsts in package_imports().items() for dst in dsts
             if RANK.get(dst, 99) >= RANK[src]]
    assert not wrong, wrong


def test_only_the_simulators_users_import_sim():
    users = {src for src, dsts in package_imports().items() if "sim" in dsts}
    assert users <= SIM_USERS, users - SIM_USERS


def test_the_checker_sees_imports():
    """The walk itself can fail: it finds known edges of every import style."""
    edges = package_imports()
    assert "errors" in edges["events"] and "geometry" in edges["io"] and "sim" in edges["nodes"]

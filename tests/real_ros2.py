"""A real ROS 2 Jazzy for the tests and benchmarks, and the package built into it as a ROS user builds it.

``../shared/ros2/ros2-jazzy-min.tar.zst`` (override: ``EVDNERF_ROS2_TARBALL``) is unpacked once into
``~/.cache/evdnerf-ros2/`` (override: ``EVDNERF_ROS2_CACHE``), keyed by the tarball's size and time.
:func:`overlay` then runs the recipe of ``docs/ros2.md`` (the lines between its ``ros2-recipe``
markers, word for word but for four substitutions: the ROS prefix for ``/opt/ros/jazzy``, a fresh
workspace for ``~/rig_ws``, a copy of this checkout for the ``git clone``, and the venv, which is
made once per set of requirements in the cache and linked into the workspace) and returns the
environment a user has after ``source install/setup.bash``.

:func:`missing` gives the reason to skip when something the recipe needs is absent.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import re
import shutil
import subprocess
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TARBALL = Path(os.environ.get("EVDNERF_ROS2_TARBALL", ROOT.parent / "shared" / "ros2" / "ros2-jazzy-min.tar.zst"))
CACHE = Path(os.environ.get("EVDNERF_ROS2_CACHE", Path.home() / ".cache" / "evdnerf-ros2"))
RECIPE_DOC = ROOT / "docs" / "ros2.md"
SYSTEM_PYTHON = "/usr/bin/python3"
#: Debian packages the recipe and the unpacked ROS need (quickstart.sh installs them as root).
DEBIAN_COMMANDS = {"zstd": "zstd", "colcon": "colcon"}


def missing() -> str | None:
    """Why the real ROS 2 cannot run here (None: it can)."""
    if not TARBALL.is_file():
        return f"the real ROS 2 tarball {TARBALL} is absent (set EVDNERF_ROS2_TARBALL)"
    if not Path(SYSTEM_PYTHON).is_file():
        return f"{SYSTEM_PYTHON} (the Python ROS 2 is built for) is absent"
    for pkg, cmd in DEBIAN_COMMANDS.items():
        if shutil.which(cmd) is None:
            return f"`{cmd}` is not installed (Debian package {pkg}; quickstart.sh installs it as root)"
    try:
        import colcon_ros  # noqa: F401  (a system package; the test's Python may not see it)
    except ImportError:
        res = subprocess.run([SYSTEM_PYTHON, "-c", "import colcon_ros, colcon_python_setup_py"], capture_output=True)
        if res.returncode:
            return "colcon's ROS extensions are not installed (Debian packages python3-colcon-ros " \
                   "python3-colcon-python-setup-py; quickstart.sh installs them as root)"
    return None


@contextmanager
def _locked(name: str):
    CACHE.mkdir(parents=True, exist_ok=True)
    with open(CACHE / f".{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield


def ros_prefix() -> Path:
    """The unpacked ROS 2 install (its ``setup.bash`` inside), unpacked on first use."""
    st = TARBALL.stat()
    target = CACHE / f"jazzy-{st.st_size}-{int(st.st_mtime)}"
    with _locked("unpack"):
        if not (target / "install" / "setup.bash").is_file():
            tmp = Path(str(target) + ".tmp")
            shutil.rmtree(tmp, ignore_errors=True)
            tmp.mkdir(parents=True)
            subprocess.run(["tar", "-C", str(tmp), "-I", "zstd", "-xf", str(TARBALL)], check=True)
            shutil.rmtree(target, ignore_errors=True)
            tmp.rename(target)
    return target / "install"


def recipe_lines() -> list[str]:
    """The shell lines of docs/ros2.md's recipe (its apt-get line left out: quickstart.sh installs those)."""
    text = RECIPE_DOC.read_text()
    m = re.search(r"<!-- ros2-recipe[^>]*-->\s*```bash\n(.*?)```\s*<!-- /ros2-recipe -->", text, re.S)
    if m is None:
        raise AssertionError(f"{RECIPE_DOC}: no ros2-recipe block")
    joined = m.group(1).replace("\\\n", " ")
    return [line.split("  #", 1)[0].strip() for line in joined.splitlines()
            if line.strip() and not line.strip().startswith(("sudo apt-get", "#"))]


def _venv_key() -> str:
    h = hashlib.sha256()
    for name in ("requirements.txt", "requirements-ros.txt"):
        h.update((ROOT / name).read_bytes())
    return h.hexdigest()[:12]


def _source_snapshot(dest: Path) -> None:
    """This checkout's files (committed, changed and new, not ignored) copied to ``dest``."""
    names = subprocess.run(["git", "-C", str(ROOT), "ls-files", "-z", "-co", "--exclude-standard"],
                           capture_output=True, check=True).stdout.split(b"\0")
    for raw in names:
        if not raw:
            continue
        rel = raw.decode()
        src = ROOT / rel
        if not os.path.lexists(src):
            continue                                   # deleted in the work tree
        out = dest / rel
        out.parent.mkdir(parents=True, exist_ok=True)
        if src.is_symlink():
            os.symlink(os.readlink(src), out)
        else:
            shutil.copy2(src, out)


@dataclass
class Overlay:
    """A built workspace: ``env`` is the environment after ``source install/setup.bash``."""
    workspace: Path
    env: dict
    symlink: bool
    build_log: str

    def run(self, args, *, env=None, timeout=120, **kw) -> subprocess.CompletedProcess:
        """Run a command (list or shell string) in the overlay's environment, capturing text output."""
        merged = {**self.env, **(env or {})}
        return subprocess.run(args, env=merged, capture_output=True, text=True, timeout=timeout,
                              shell=isinstance(args, str), executable="/bin/bash" if isinstance(args, str) else None,
                              **kw)

    def popen(self, args, *, env=None, **kw) -> subprocess.Popen:
        merged = {**self.env, **(env or {})}
        return subprocess.Popen(args, env=merged, text=True, **kw)

    @property
    def python(self) -> str:
        return str(self.workspace / "venv" / "bin" / "python")


def overlay(workspace: Path, *, symlink: bool) -> Overlay:
    """Run the recipe into ``workspace`` (new), with or without ``--symlink-install``."""
    prefix = ros_prefix()
    workspace = Path(workspace)
    venv = CACHE / f"venv-{_venv_key()}"
    script = ["set -eo pipefail"]
    for line in recipe_lines():
        line = line.replace("/opt/ros/jazzy", str(prefix)).replace("~/rig_ws", str(workspace))
        if line.startswith("git clone"):
            script.append(f"cp -a {workspace}.src src/rig")
            continue
        if "-m venv" in line:
            # the venv once per requirements (its pip install is then a quick no-op), linked in
            script.append(f"[ -x {venv}/bin/python ] || {re.sub(r' venv$', ' ' + str(venv), line)}")
            script.append(f"ln -s {venv} venv")
            continue
        if line.startswith("touch venv/COLCON_IGNORE"):
            script.append(f"touch {venv}/COLCON_IGNORE")
            continue
        if line.startswith("python -m colcon build"):
            line = line.replace(" --symlink-install", "") + (" --symlink-install" if symlink else "")
        script.append(line)
    script.append("env -0 > .overlay-env")
    _source_snapshot(Path(f"{workspace}.src"))
    env = {k: v for k, v in os.environ.items() if not k.startswith(("ROS_", "AMENT_", "COLCON_", "VIRTUAL_ENV",
                                                                    "PYTHON", "CYCLONEDDS", "RMW_"))}
    env["PATH"] = os.pathsep.join(p for p in env.get("PATH", "").split(os.pathsep) if ".venv" not in p)
    env["HOME"] = os.environ.get("HOME", "/root")
    with _locked("venv"):
        res = subprocess.run(["bash", "-c", "\n".join(script)], env=env, capture_output=True, text=True, timeout=1800)
    log = res.stdout + res.stderr
    if res.returncode:
        raise RuntimeError(f"the docs/ros2.md recipe failed in {workspace} (exit {res.returncode}):\n{log[-4000:]}")
    raw = (workspace / ".overlay-env").read_bytes().split(b"\0")
    out = dict(item.decode().split("=", 1) for item in raw if b"=" in item)
    out.update(RMW_IMPLEMENTATION="rmw_cyclonedds_cpp", PYTHONUNBUFFERED="1")
    return Overlay(workspace, out, symlink, log)

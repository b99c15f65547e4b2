"""Where the package's data lives: ``config/`` (parameter YAML, scene presets) and ``firmware/``.

One folder holds them, found in this order:

1. the source checkout this module was imported from (``pip install -e .``, ``colcon build
   --symlink-install``, or the tree itself on ``PYTHONPATH``): the folder holding ``package.xml``
   next to ``evdnerf_ros/``;
2. the ament install this module was imported from (``colcon build``: ``<prefix>/lib/pythonX.Y/
   site-packages/evdnerf_ros`` -> ``<prefix>/share/rig``), as ``ament_index_python``'s
   ``get_package_share_directory`` would answer for it;
3. the first ``share/rig`` registered in the ament index of ``AMENT_PREFIX_PATH``;
4. ``sys.prefix/share/rig`` (a plain ``pip install .``, which installs setup.py's data_files there).
"""

from __future__ import annotations

import os
import sys
from functools import lru_cache
from pathlib import Path

PACKAGE = "rig"
_MODULE_DIR = Path(__file__).resolve().parent


def _is_share(path: Path) -> bool:
    return (path / "package.xml").is_file() and (path / "config").is_dir()


def _candidates():
    yield _MODULE_DIR.parent                                  # 1. source checkout
    for parent in _MODULE_DIR.parents[:4]:                    # 2. the install we were imported from
        yield parent / "share" / PACKAGE                      #    (site-packages, pythonX.Y, lib, prefix)
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):   # 3. ament index
        if prefix and (Path(prefix) / "share" / "ament_index" / "resource_index" / "packages" / PACKAGE).is_file():
            yield Path(prefix) / "share" / PACKAGE
    yield Path(sys.prefix) / "share" / PACKAGE                # 4. pip's data_files


@lru_cache(maxsize=None)
def share_dir() -> Path:
    """The package's data folder (see the module docstring); FileNotFoundError names what was searched."""
    searched = []
    for path in _candidates():
        if _is_share(path):
            return path
        searched.append(str(path))
    raise FileNotFoundError(f"the {PACKAGE} package's data (package.xml, config/) is in none of: "
                            f"{', '.join(dict.fromkeys(searched))}; reinstall the package (pip install ., or "
                            "colcon build in a ROS workspace)")


def is_source_checkout() -> bool:
    """True when the data folder is the source tree itself (writable build outputs may go there)."""
    return share_dir() == _MODULE_DIR.parent


def user_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/rig`` (default ``~/.cache/rig``): build outputs of an installed package."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / PACKAGE

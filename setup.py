"""ament_python package `rig`: the EvDNeRF rig toolkit (python packages evdnerf_ros and rig)."""

from glob import glob
from pathlib import Path

from setuptools import find_packages, setup

PACKAGE = "rig"


def _requirements() -> list[str]:
    """requirements.txt without its comments (the one list of run-time dependencies)."""
    text = (Path(__file__).resolve().parent / "requirements.txt").read_text()
    return [line.split("#", 1)[0].strip() for line in text.splitlines() if line.split("#", 1)[0].strip()]

setup(
    name=PACKAGE,
    version="0.1.0",
    description="EvDNeRF rig toolkit: event-camera capture, sync, training and event publishing",
    packages=find_packages(include=["evdnerf_ros", "evdnerf_ros.*", "rig", "rig.*"]),
    package_data={"evdnerf_ros.io": ["msg/*/msg/*.msg", "msg/ros1/*/msg/*.msg"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/config/scenes", glob("config/scenes/*.yaml")),
        # the servo firmware's sources: the virtual rig builds and runs them, `rig flash` flashes them
        (f"share/{PACKAGE}/firmware", ["firmware/Makefile", "firmware/main.c", "firmware/PROTOCOL.md",
                                       "firmware/README.md"]),
        (f"share/{PACKAGE}/firmware/core", glob("firmware/core/*.[ch]")),
        (f"share/{PACKAGE}/firmware/harness", glob("firmware/harness/*.c")),
    ],
    python_requires=">=3.10",
    install_requires=_requirements(),
    extras_require={
        "test": ["pytest>=7", "pytest-xdist>=3", "hypothesis>=6", "mcap>=1.1",
                 "mcap-ros2-support>=0.5", "expelliarmus==1.1.12",
                 "evlib==0.13.2",  # peer codec and peer simulator in tests/benchmarks
                 "faery==0.7.1",  # aestream's I/O library: peer RAW reader / writer (its `% t0` in us)
                 "neuromorphic-drivers>=0.18,<0.19",  # peer USB driver of the camera twins
                 "eclipse-zenoh>=1.0,<2"],  # Zenoh transport and its independent peer (tests/test_ros_zenoh.py)
        "zenoh": ["eclipse-zenoh>=1.0,<2"],  # RMW_IMPLEMENTATION=rmw_zenoh_cpp (evdnerf_ros.ros.zenoh_transport)
    },
    entry_points={"console_scripts": ["evdnerf = evdnerf_ros.cli:run",
                                      "event_publisher = evdnerf_ros.nodes.event_publisher:main",
                                      "capture = rig.capture_cli:main"],
                  # plugin commands of the `evdnerf` CLI (evdnerf_ros never imports rig)
                  "evdnerf.commands": ["rig = rig.cli:register"],
                  # session sources of `evdnerf demo --source` (evdnerf_ros.demo finds them here)
                  "evdnerf.session_sources": ["virtual-rig = rig.demo_capture:capture_demo_session"]},
    zip_safe=True,
)

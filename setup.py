"""ament_python package `rig`: the EvDNeRF rig toolkit (python packages evdnerf_ros and rig)."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "rig"

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
    ],
    python_requires=">=3.10",
    # Versions: torch is pinned exactly because any looser spec pulls GBs of CUDA wheels;
    # cyclonedds is pinned exactly because evdnerf_ros.ros.transport's raw-CDR fast path
    # calls the binding's private low-level writer/reader (tests/test_ros_transport.py checks it).
    install_requires=[
        "numpy>=1.24",
        "pyyaml>=6",
        "h5py>=3.8",
        "matplotlib>=3.7",
        "tqdm>=4.60",
        "rosbags>=0.11,<0.12",
        "trimesh>=4",  # OBJ/PLY/GLB mesh loading for scene objects
        "torch==2.13.0",
        "numba==0.68.1",  # EVT 2.0 / 3.0 decode/encode hot loops compiled to C speed
        "pyserial>=3.5",  # the servo-rig firmware's serial link (rig.servo)
        "cyclonedds==11.0.1",  # ROS 2-compatible DDS transport; private raw-CDR API, see above
        "pyusb>=1.2",  # camera drivers: finding devices, control transfers (rig.camera)
        "libusb1>=3.1",  # python-libusb1: queued async bulk streaming (rig.camera.streaming)
        "opencv-contrib-python-headless>=4.8",  # aruco/ChArUco detection and calibration (evdnerf_ros.calib)
    ],
    extras_require={
        "test": ["pytest>=7", "pytest-xdist>=3", "hypothesis>=6", "mcap>=1.1",
                 "mcap-ros2-support>=0.5", "expelliarmus==1.1.12",
                 "evlib==0.13.2",  # peer codec and peer simulator in tests/benchmarks
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

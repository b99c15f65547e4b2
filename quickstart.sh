#!/usr/bin/env bash
# The README's two quickstart commands:
#   bash quickstart.sh demo   # set up, then run the end-to-end demo on the virtual rig
#   bash quickstart.sh test   # set up, then run the whole test suite
# Set-up is idempotent: a .venv in this folder, `pip install -e .[test]` (torch pinned to
# 2.13.0 in setup.py), and, when run as root, the Debian packages the toolkit needs.
set -euo pipefail
cd "$(dirname "$0")"

job=${1:-}
case "$job" in
  demo|test) shift ;;
  *) echo "usage: bash quickstart.sh demo|test [extra arguments]" >&2; exit 2 ;;
esac

PYTHON=${PYTHON:-python3}
APT_PACKAGES="python3-venv python3-dev gcc"

apt_install() {
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "quickstart: installing Debian packages: $*"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" >/dev/null
  else
    echo "quickstart: please install the Debian packages: $* (run this script as root to do it automatically)" >&2
    return 1
  fi
}

if [ ! -x .venv/bin/python ]; then
  if ! "$PYTHON" -m venv .venv 2>/dev/null; then
    rm -rf .venv
    apt_install $APT_PACKAGES
    "$PYTHON" -m venv .venv
  fi
fi

# Optional Debian packages: installed when run as root, else the tests that need them are
# skipped (with the reason). Checked with dpkg so an installed machine never runs apt.
ensure_packages() {
  what=$1; shift
  missing=""
  if command -v dpkg >/dev/null; then
    for pkg in "$@"; do
      dpkg -s "$pkg" >/dev/null 2>&1 || missing="$missing $pkg"
    done
  fi
  [ -n "$missing" ] || return 0
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "quickstart: installing Debian packages for $what:$missing"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $missing >/dev/null \
      || echo "quickstart: could not install$missing; the tests of $what will be skipped" >&2
  else
    echo "quickstart: the tests of $what are skipped until these Debian packages are installed:$missing (run this script as root to install them)" >&2
  fi
}

# The servo-rig firmware (firmware/): avr-gcc + avr-libc build it, simavr + libsimavr-dev run it
# in the virtual Arduino, avrdude flashes it, arduino-core-avr holds the bootloader the
# flashing test runs.
FIRMWARE_PACKAGES="gcc-avr avr-libc avrdude simavr libsimavr-dev arduino-core-avr make"
ensure_packages "the servo firmware" $FIRMWARE_PACKAGES

# Virtual USB cameras (rig/camera/virtual): umockdev serves emulated devices to the real
# libusb; its Python API comes through GObject introspection (python3-gi, a Debian package),
# made importable in the .venv by a .pth file pointing at a folder that holds only a symlink
# to the system's gi (works for the venv's CPython 3.11; no build). Without them the camera
# tests are skipped with the reason.
USB_PACKAGES="umockdev gir1.2-umockdev-1.0 python3-gi libusb-1.0-0"
ensure_packages "the virtual USB cameras" $USB_PACKAGES

# The independent DDS peer of the ROS 2 tests (tests/fastdds_peer, built with cmake during the
# run): eProsima Fast DDS 2.9, ROS 2's default middleware; fastddsgen / fastdds-tools are its
# type generator and the `fastdds` discovery tool.
FASTDDS_PACKAGES="libfastrtps-dev fastddsgen fastdds-tools cmake g++"
ensure_packages "the Fast DDS peer" $FASTDDS_PACKAGES
# The real ROS 2 of the ROS tests (tests/real_ros2.py: ../shared/ros2's Jazzy, unpacked into
# ~/.cache/evdnerf-ros2, and our package built into it with colcon as docs/ros2.md says): its
# run-time libraries and Python modules, and Debian's colcon with the extensions a ROS workspace uses.
ROS2_PACKAGES="zstd cyclonedds-dev libspdlog-dev libyaml-dev python3-numpy python3-yaml python3-lark
  python3-netifaces python3-psutil python3-osrf-pycommon python3-argcomplete python3-packaging
  python3-importlib-metadata python3-catkin-pkg python3-empy libsqlite3-0 libzstd1 liblz4-1 libyaml-cpp0.7
  libconsole-bridge1.0 libtinyxml2-9 python3-venv colcon python3-colcon-core python3-colcon-ros
  python3-colcon-python-setup-py python3-colcon-bash python3-colcon-recursive-crawl
  python3-colcon-package-selection python3-colcon-parallel-executor python3-colcon-output
  python3-colcon-library-path python3-colcon-package-information"
ensure_packages "the real ROS 2" $ROS2_PACKAGES
if [ -d /usr/lib/python3/dist-packages/gi ] && ! .venv/bin/python -c "import gi" 2>/dev/null; then
  site=$(.venv/bin/python -c "import sysconfig; print(sysconfig.get_paths()['purelib'])")
  mkdir -p .venv/system-gi
  ln -sfn /usr/lib/python3/dist-packages/gi .venv/system-gi/gi
  echo "$PWD/.venv/system-gi" > "$site/system-gi.pth"
  .venv/bin/python -c "import gi" 2>/dev/null \
    || echo "quickstart: the system's python3-gi does not load in the .venv; the virtual camera tests will be skipped" >&2
fi

# Reinstall only when the package definition changed since the last set-up.
stamp=.venv/.quickstart-stamp
want=$(cat setup.py setup.cfg package.xml pyproject.toml requirements.txt | sha256sum | cut -d' ' -f1)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e '.[test]'
  echo "$want" > "$stamp"
fi

case "$job" in
  demo) exec .venv/bin/python -m evdnerf_ros demo --overwrite "$@" ;;
  test)
    # Tests paced to real time (the virtual rig, DDS between processes; marked `realtime`) need the
    # machine to themselves: they run after the rest, one at a time. Exit 5 = nothing selected.
    status=0
    .venv/bin/python -m pytest -q -n 2 -p no:cacheprovider -m "not realtime" "$@" || status=$?
    [ "$status" = 5 ] && status=0
    rt=0
    .venv/bin/python -m pytest -q -p no:cacheprovider -m realtime "$@" || rt=$?
    [ "$rt" = 5 ] && rt=0
    [ "$status" = 0 ] && status=$rt
    exit "$status" ;;
esac

import itertools
import os
import time
from pathlib import Path

import numpy as np
import pytest

from evdnerf_ros.events import make_events


def pytest_configure(config):
    """Under pytest-xdist every worker shares the cores: one torch thread each, or the
    workers' thread pools oversubscribe the machine (a 24 s test took 126 s)."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        import torch

        torch.set_num_threads(1)


#: Modules whose tests are paced to real time besides the virtual rig's (DDS between processes).
REALTIME_MODULES = {"test_ros_dds_nodes", "test_ros_graph", "test_ros2_real"}


def pytest_collection_modifyitems(config, items):
    """Mark the tests paced to real time (``realtime``): the closed-loop virtual rig (firmware in
    simavr, camera twin) and DDS between processes miss their deadlines when another worker
    trains a field on the second of two cores, so ``quickstart.sh test`` runs them after the
    rest, one at a time."""
    for item in items:
        if {"rig_lock", "virtual_rig"} & set(getattr(item, "fixturenames", ())) \
                or item.module.__name__.rsplit(".", 1)[-1] in REALTIME_MODULES:
            item.add_marker(pytest.mark.realtime)


def random_events(rng, n, width=64, height=48, t0=0, span=1_000_000_000):
    t = np.sort(rng.integers(t0, t0 + span, n))
    return make_events(t, rng.integers(0, width, n), rng.integers(0, height, n),
                       rng.choice(np.array([-1, 1], np.int8), n))


class NoEvents:
    """A training set with every view's events gone (a scene where nothing moved)."""

    def __init__(self, ts):
        self.ts = ts

    def __getattr__(self, name):
        return getattr(self.ts, name)

    def iter_events(self, view, *args, **kwargs):
        return iter(())


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def built():
    """The servo firmware built once for the virtual Arduino (skips when avr-gcc / simavr are missing)."""
    from rig import virtual_arduino as va_mod

    missing = [p for p in va_mod.missing_tools() if p != "avrdude"]
    if missing:
        pytest.skip("firmware tools missing: install the Debian packages " + " ".join(missing))
    return va_mod.build()


@pytest.fixture(scope="session")
def tiny_train_h5(tmp_path_factory):
    """A tiny training set (fork, 32x32 with 2x2 supersampling, 4 training + 2 validation views
    + 1 moving validation view, 20 Hz blurred frames, ground-truth offsets), built once."""
    from evdnerf_ros.session.convert import run_convert
    from evdnerf_ros.sim.simulate import SimulationOptions, simulate_session

    tmp = tmp_path_factory.mktemp("tiny_train")
    simulate_session("fork", tmp / "s", SimulationOptions(
        views=4, val_views=2, moving_views=1, resolution=(32, 32), frame_rate_hz=20, blur_samples=2, gt_times=0,
        supersample=2, jobs=1, min_step_ns=2_000_000), log=lambda *_: None)
    run_convert(tmp / "s", tmp / "t.h5", offsets="ground-truth", log=lambda *_: None)
    return tmp / "t.h5"


@pytest.fixture(scope="session")
def sweep_h5(tiny_train_h5, tmp_path_factory):
    """The tiny fork set with its moving camera (``moving_00``) made a training view."""
    import shutil

    import h5py

    out = tmp_path_factory.mktemp("sweep") / "sweep.h5"
    shutil.copyfile(tiny_train_h5, out)
    with h5py.File(out, "r+") as f:
        f["views"]["moving_00"].attrs["split"] = "train"
    return out


def child_pids(pid: int) -> set[int]:
    """Processes whose parent is `pid` (Linux /proc): the workers a signal test watches."""
    kids = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            kids.add(int(stat.parent.name))
    return kids


def pid_alive(pid: int) -> bool:
    """A process that still runs (zombies and dead ones do not)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state not in ("Z", "X")


# --------------------------------------------------------------------------- the closed-loop virtual rig

#: The virtual rig's scene size and render rate in tests: what this machine renders near real
#: time while a test suite runs (the fork's renders cost ~11 ms here), leaving the simulated
#: Arduino its core.
RIG_SCENE = (32, 24)
RIG_RATE_HZ = 150


@pytest.fixture
def rig_lock():
    """One closed-loop virtual rig at a time on this machine, whichever worker runs it: two
    (firmware in simavr + a renderer each, paced to real time) overload two cores. A lock file,
    released by the kernel if a worker dies."""
    import fcntl
    import os
    import tempfile
    from pathlib import Path

    with open(Path(tempfile.gettempdir()) / f"evdnerf-virtual-rig-{os.getuid()}.lock", "w") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


@pytest.fixture
def virtual_rig(built, rig_lock):
    """A running closed-loop virtual rig (rig.virtual_rig), one at a time (``rig_lock``); skips
    with the reason without umockdev or the firmware tools."""
    from rig.camera.virtual.usb import umockdev_available
    from rig.virtual_arduino import missing_tools

    ok, why = umockdev_available()
    if not ok:
        pytest.skip(f"umockdev: {why}")
    missing = [p for p in missing_tools() if p != "avrdude"]
    if missing:
        pytest.skip(f"firmware tools missing: {missing}")
    from rig.virtual_rig import VirtualRig

    with VirtualRig(scene_size=RIG_SCENE, rate_hz=RIG_RATE_HZ) as vr:
        yield vr


# a random start for this process, then one domain after the other
_domains_drawn = itertools.count((os.getpid() + time.time_ns() // 1000) % 1000)


def ros_domain() -> int:
    """A DDS domain (1..200) for one test, from a range of its own for each xdist worker, so
    tests running at the same time in two workers never share a domain; within a worker the
    domains follow each other from a random start, so no two tests of one run share one either
    (a node or peer process of an earlier test that is still shutting down would otherwise serve
    its /tf_static or discovery sample to a later test that drew the same domain)."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    count = max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")))
    index = int(worker[2:]) if worker[2:].isdigit() else 0
    size = max(1, 200 // count)
    return 1 + (index % count) * size + next(_domains_drawn) % size

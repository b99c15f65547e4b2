"""The closed-loop virtual rig: the real firmware, a camera twin and the simulated scene, wired as
on the bench.

Parts and wiring (issue 15, item 4):

* the **virtual Arduino** (rig.virtual_arduino): the real firmware in simavr, paced to real time,
  behind a pseudo-terminal that the capture node opens as the servo port;
* its **pins** (rig.pin_feed): D9's pulse widths drive the scene's servo joint through the
  firmware's own pulse-to-angle mapping (read from the firmware with ``GET LIMITS``), D10's the
  turntable (the camera's view), and D8's trigger pulse reaches the twin's trigger input, so the
  EXT_TRIGGER edges in the stream come from the firmware;
* a **camera twin** (rig.camera.virtual) on an emulated USB bus (umockdev), streaming what the
  scene looks like at the angles it is actually given (rig.camera.virtual.rig_source), rendered at
  ``scene_size`` in the sensor's centre, ``latency_us`` behind real time so that every pin edge is
  known before the stream reaches its time.

The camera driver must run in another process started with :meth:`VirtualRig.env` (umockdev's
preload); the servo port works from any process. Truth for tests: ``trigger_log`` (each D8 edge:
host time, the sensor time the twin placed it at, and whether it was on time), the twin's
``sensor_zero_host_ns`` per start, ``calibration()`` (the twin's true intrinsics).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np

from evdnerf_ros.errors import InputError

from .pin_feed import PinFeed, follow

#: Twin models the virtual rig can host and their driver / twin classes.
TWIN_CLASSES = {
    "evk4": ("rig.camera.evk4:EVK4", "rig.camera.virtual.evk4:VirtualEVK4"),
    "dvxplorer": ("rig.camera.dvxplorer:DVXplorer", "rig.camera.virtual.dvxplorer:VirtualDVXplorer"),
    "davis346": ("rig.camera.davis346:DAVIS346", "rig.camera.virtual.davis346:VirtualDAVIS346"),
}


def _load(target: str):
    import importlib

    mod, cls = target.split(":")
    return getattr(importlib.import_module(mod), cls)


@dataclass
class TriggerRecord:
    host_ns: int            # when the firmware raised D8 (host monotonic clock)
    sensor_ns: int | None   # where the twin put the rising edge (None: not streaming / input off)
    on_time: bool           # the edge landed at its true sensor time
    stream: int = 0         # the camera twin's stream then (``RigDrivenSource.stream``: one per recorded view)


#: Reply timeout (s) of the servo client talking to the simulated board (rig.servo; real boards: 1 s).
SIMULATED_SERVO_TIMEOUT_S = 5.0


@dataclass
class VirtualRig:
    """See the module docstring; a context manager."""
    model: str = "evk4"
    scene: str = "fork"
    scene_size: tuple[int, int] = (64, 48)
    rate_hz: float = 500.0
    latency_us: int = 60_000
    eeprom: str | None = None
    trigger_log: list[TriggerRecord] = field(default_factory=list)

    def __post_init__(self):
        if self.model not in TWIN_CLASSES:
            raise InputError(f"virtual rig: camera model {self.model!r} is not one of {sorted(TWIN_CLASSES)}")
        self.arduino = self.bus = self.twin = self.source = self.feed = None
        self._stop = threading.Event()
        self._thread = None

    # --- lifetime ------------------------------------------------------------------------
    def __enter__(self) -> "VirtualRig":
        try:
            self.start()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def start(self) -> None:
        from .camera.virtual.rig_source import RigDrivenSource
        from .camera.virtual.scene_source import CenteredSource
        from .camera.virtual.usb import VirtualUsbBus, umockdev_available
        from .servo import ServoClient
        from .virtual_arduino import VirtualArduino

        ok, why = umockdev_available()
        if not ok:
            raise InputError(f"the virtual rig needs umockdev for its camera: {why}; run `bash quickstart.sh` "
                             "as root to install it")
        driver = _load(TWIN_CLASSES[self.model][0])
        w, h = map(int, self.scene_size)
        if w > driver.width or h > driver.height:
            raise InputError(f"scene size {w}x{h} does not fit the {driver.width}x{driver.height} sensor of "
                             f"{self.model}; choose a smaller scene size")
        self.arduino = VirtualArduino(pace=True, eeprom=self.eeprom)
        port = self.arduino.start()
        with ServoClient(port) as servo:         # the firmware's own mapping and power-up angle
            limits, profile = servo.get_limits(), servo.get_profile()
        self.limits, self.profile = limits, profile
        self.feed = PinFeed(self.arduino.log_path, pulse_min_us=limits.pulse_min_us,
                            pulse_max_us=limits.pulse_max_us, servo_start_deg=profile.start_deg)
        self.source = RigDrivenSource(self.scene, w, h, self.feed, rate_hz=self.rate_hz)
        self.twin = _load(TWIN_CLASSES[self.model][1])(CenteredSource(self.source, driver.width, driver.height),
                                                       latency_us=self.latency_us)
        self.source.zero_host_ns = lambda: self.twin.sensor_zero_host_ns
        self.driver = driver
        self.bus = VirtualUsbBus()
        self.bus.__enter__()
        self.bus.add(self.twin)
        self._thread = follow(self.feed, self._trigger, self._stop)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2)
            self._thread = None
        if self.bus is not None:
            self.bus.close()
            self.bus = None
        if self.source is not None:
            self.source.close()
            self.source = None
        if self.arduino is not None:
            self.arduino.close()
            self.arduino = None

    # --- wiring ---------------------------------------------------------------------------
    def _trigger(self, host_ns: int) -> None:
        """D8 rose at host_ns: the pulse reaches the twin's trigger input at that instant."""
        twin = self.twin
        zero = twin.sensor_zero_host_ns
        at_us = (host_ns - zero) // 1000
        got = twin.pulse_trigger(width_us=1000, at_us=at_us) if at_us >= 0 else None
        self.trigger_log.append(TriggerRecord(host_ns, None if got is None else int(got[0]),
                                              got is not None and got[0] == 1000 * at_us, self.source.stream))

    # --- what the capture node needs ------------------------------------------------------------
    @property
    def port(self) -> str:
        return self.arduino.port

    @property
    def camera_serial(self) -> str:
        return self.twin.serial

    def env(self, base: dict | None = None) -> dict:
        """The environment of a process that runs the camera driver against the twin (and the
        servo client against the simulated board, which may answer late on a busy machine)."""
        env = self.bus.env(base)
        env.setdefault("EVDNERF_SERVO_TIMEOUT_S", str(SIMULATED_SERVO_TIMEOUT_S))
        return env

    def intrinsics(self) -> np.ndarray:
        """The twin's true K on the full sensor (the scene's camera, centred)."""
        cam, inner = self.source.camera, self.twin.source
        K = np.array(cam.K, np.float64)
        K[0, 2] += inner.dx
        K[1, 2] += inner.dy
        return K

    def ring(self):
        """The scene's camera ring: the rig geometry the capture records poses with."""
        return self.source.scene.cameras.ring

    def calibration_document(self) -> dict:
        """A calibration file (the layout `evdnerf calibrate` writes) holding the twin's truth."""
        return {"width": int(self.driver.width), "height": int(self.driver.height),
                "K": self.intrinsics().tolist(), "D": [0.0] * 5, "distortion_model": "plumb_bob",
                "source": f"virtual rig truth ({self.model} twin, scene {self.scene})"}

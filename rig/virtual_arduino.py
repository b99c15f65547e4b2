"""The virtual Arduino: the real servo-rig firmware running in simavr behind a pseudo-terminal.

``VirtualArduino`` builds ``rig_servo.hex`` and ``virtual_arduino`` from ``firmware/`` with ``make``
when they are missing or older than their sources (into ``firmware/build`` of a source checkout; for
an installed package, whose ``share/rig/firmware`` may be read-only, into ``~/.cache/rig/firmware/``), starts the harness and gives the pty
path (open it with pyserial, or ``rig.servo.ServoClient``).  The harness logs every edge of
D8 (trigger), D9 (scene servo) and D10 (turntable) with its simulated time; ``pin_log()``
reads that log.  Unpaced the chip runs several times faster than real time (device
microseconds then pass faster than host seconds); ``pace=True`` keeps it at real time (for
avrdude and host-timing measurements).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evdnerf_ros.errors import EvdnerfError, InputError



def _firmware_dirs() -> tuple[Path, Path]:
    """(sources, build outputs): the package data's firmware/ (evdnerf_ros.share) and where make writes."""
    import hashlib

    from evdnerf_ros.share import is_source_checkout, share_dir, user_cache_dir

    try:
        src = share_dir() / "firmware"
    except FileNotFoundError:
        src = Path(__file__).resolve().parents[1] / "firmware"     # build() then says it is missing
        return src, src / "build"
    if is_source_checkout():
        return src, src / "build"
    return src, user_cache_dir() / "firmware" / hashlib.sha256(str(src).encode()).hexdigest()[:12]


FIRMWARE_DIR, BUILD_DIR = _firmware_dirs()
FIRMWARE_HEX = BUILD_DIR / "rig_servo.hex"
HARNESS = BUILD_DIR / "virtual_arduino"
#: Debian 12 packages the firmware, the harness and flashing need.
DEBIAN_PACKAGES = ("gcc-avr", "avr-libc", "avrdude", "simavr", "libsimavr-dev")
#: The Arduino bootloaders shipped by Debian (used to test flashing end to end).
BOOTLOADER_PACKAGE = "arduino-core-avr"
ATMEGABOOT_HEX = Path("/usr/share/arduino/hardware/arduino/avr/bootloaders/atmega/"
                      "ATmegaBOOT_168_atmega328.hex")

PIN_TRIGGER, PIN_SERVO, PIN_TURNTABLE = "D8", "D9", "D10"
#: pin-log dtype: simulated time in ns since power-up (int64), pin name, level, and the host's
#: time.monotonic_ns() when the harness simulated the edge (its place in physical time)
PIN_DTYPE = np.dtype([("t_ns", "<i8"), ("pin", "U3"), ("level", "u1"), ("host_ns", "<i8")])


class FirmwareToolsMissing(EvdnerfError):
    """avr-gcc, avr-libc or the simavr headers/library are not installed."""


class VirtualArduinoError(EvdnerfError):
    """The harness failed to build or start."""


class EepromFileError(VirtualArduinoError, InputError):
    """The --eeprom image cannot be read, written or saved, or is not a 1024-byte image."""


#: Bytes of the ATmega328P's EEPROM, the exact size of an --eeprom image file.
EEPROM_SIZE = 1024


def check_eeprom_file(path) -> Path:
    """Check an EEPROM image path before the chip starts, so settings are never lost silently.

    An existing file must be a regular, readable and writable file of EEPROM_SIZE bytes; a new
    one needs an existing, writable folder (the harness writes the image there through a temp
    file and a rename).  Raises EepromFileError naming the path and the fix.
    """
    path = Path(path)
    folder = path.parent
    if not folder.is_dir():
        raise EepromFileError(f"{path}: EEPROM image folder {folder} does not exist; create it "
                              "or choose another --eeprom path")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise EepromFileError(f"{path}: EEPROM image folder {folder} is not writable, so the "
                              "settings could not be saved; choose another --eeprom path")
    if not os.path.lexists(path):
        return path                       # first run: the chip starts erased
    if not path.is_file():
        raise EepromFileError(f"{path}: not a regular file; give an EEPROM image file path "
                              "for --eeprom")
    try:
        with open(path, "r+b"):
            pass
    except OSError as exc:
        raise EepromFileError(f"{path}: EEPROM image not readable and writable ({exc.strerror}); "
                              "fix its permissions or choose another --eeprom path") from None
    size = path.stat().st_size
    if size != EEPROM_SIZE:
        raise EepromFileError(f"{path}: EEPROM image is {size} bytes, expected {EEPROM_SIZE} "
                              "(corrupt or not an ATmega328P image); move it away to start with "
                              "an erased EEPROM")
    return path


def missing_tools() -> list[str]:
    """Debian packages (of DEBIAN_PACKAGES) whose files are absent on this machine."""
    checks = {
        "gcc-avr": lambda: shutil.which("avr-gcc") is not None,
        "avr-libc": lambda: Path("/usr/lib/avr/include/avr/io.h").exists(),
        "avrdude": lambda: shutil.which("avrdude") is not None,
        "simavr": lambda: any(Path("/usr/lib").glob("*/libsimavr.so.*"))
        or shutil.which("simavr") is not None,
        "libsimavr-dev": lambda: Path("/usr/include/simavr/sim_avr.h").exists(),
    }
    return [pkg for pkg, ok in checks.items() if not ok()]


def _install_hint(pkgs) -> str:
    return f"apt-get install -y {' '.join(pkgs)} (or run `bash quickstart.sh test` as root)"


def _stale(target: Path, sources) -> bool:
    if not target.exists():
        return True
    t = target.stat().st_mtime
    return any(p.stat().st_mtime > t for p in sources)


_build_lock = threading.Lock()


def build(force: bool = False) -> Path:
    """Run ``make`` in firmware/ when an output is missing or older than its sources."""
    if not (FIRMWARE_DIR / "Makefile").is_file():
        raise VirtualArduinoError(f"{FIRMWARE_DIR}: the firmware sources are not installed; reinstall the "
                                  "package (its setup.py installs them under share/rig/firmware)")
    sources = [p for p in FIRMWARE_DIR.rglob("*") if p.is_file() and p.suffix in (".c", ".h")
               and BUILD_DIR not in p.parents and "rig_servo" not in p.parts]
    sources.append(FIRMWARE_DIR / "Makefile")
    with _build_lock:
        if not force and not _stale(FIRMWARE_HEX, sources) and not _stale(HARNESS, sources):
            return BUILD_DIR
        need = [p for p in missing_tools() if p != "avrdude"]
        if need or shutil.which("make") is None:
            raise FirmwareToolsMissing(
                "building the firmware needs the Debian packages "
                f"{', '.join(need or ['make'])}; install them: "
                + _install_hint(need or ["make"]))
        # a private build folder renamed into place: parallel builds never see half files
        BUILD_DIR.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=".tmp-", dir=BUILD_DIR))
        try:
            res = subprocess.run(["make", "-C", str(FIRMWARE_DIR), f"BUILD={tmp}"],
                                 capture_output=True, text=True)
            if res.returncode != 0:
                raise VirtualArduinoError(f"{FIRMWARE_DIR}: make failed:\n{res.stderr[-2000:]}")
            for f in tmp.iterdir():
                os.replace(f, BUILD_DIR / f.name)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    return BUILD_DIR


def read_pin_log(path) -> np.ndarray:
    """Parse a harness log into PIN_DTYPE records (RESET lines are skipped)."""
    return parse_pin_lines(Path(path).read_text().splitlines())


def parse_pin_lines(lines) -> np.ndarray:
    """PIN_DTYPE records of complete harness log lines (RESET lines are skipped)."""
    rows = []
    for line in lines:
        parts = line.split()
        if len(parts) != 4:
            continue
        whole, _, frac = parts[0].partition(".")
        t_ns = int(whole) * 1000 + (int(frac.ljust(4, "0")[:4]) // 10 if frac else 0)
        rows.append((t_ns, parts[1], int(parts[2]), int(parts[3])))
    return np.array(rows, dtype=PIN_DTYPE)


@dataclass
class Pulse:
    start_ns: int
    width_ns: int


def pulses(log: np.ndarray, pin: str) -> list[Pulse]:
    """High pulses of one pin (rising edge, width) from a pin log."""
    sel = log[log["pin"] == pin]
    out, rise = [], None
    for t, level in zip(sel["t_ns"].tolist(), sel["level"].tolist()):
        if level and rise is None:
            rise = t
        elif not level and rise is not None:
            out.append(Pulse(rise, t - rise))
            rise = None
    return out


class VirtualArduino:
    """Start the harness; use as a context manager (``with VirtualArduino() as va: va.port``)."""

    def __init__(self, firmware: str | os.PathLike | None = FIRMWARE_HEX, *, pace: bool = False,
                 bootloader: str | os.PathLike | None = None,
                 eeprom: str | os.PathLike | None = None, eeprom_stuck: bool = False,
                 workdir: str | os.PathLike | None = None, start_timeout: float = 10.0):
        self.firmware = Path(firmware) if firmware is not None else None
        self.bootloader = Path(bootloader) if bootloader is not None else None
        self.pace = pace
        self.eeprom = Path(eeprom) if eeprom is not None else None
        self.eeprom_stuck = eeprom_stuck      # fault for tests: EEPROM writes do not stick
        self.save_error: str | None = None
        self._own_dir = workdir is None
        self.workdir = Path(workdir) if workdir else Path(tempfile.mkdtemp(prefix="virtual-arduino-"))
        self.log_path = self.workdir / "pins.log"
        self.start_timeout = start_timeout
        self.proc: subprocess.Popen | None = None
        self.port: str | None = None

    def start(self) -> str:
        if self.proc is not None:
            return self.port
        if self.eeprom is not None:
            check_eeprom_file(self.eeprom)
        build()
        self.workdir.mkdir(parents=True, exist_ok=True)
        if self.bootloader is not None and not self.bootloader.exists():
            raise VirtualArduinoError(f"{self.bootloader}: bootloader hex not found (Debian package "
                                      f"{BOOTLOADER_PACKAGE})")
        cmd = [str(HARNESS), "--log", str(self.log_path)]
        if self.pace:
            cmd.append("--pace")
        if self.eeprom is not None:
            cmd += ["--eeprom", str(self.eeprom)]
        if self.eeprom_stuck:
            cmd.append("--eeprom-stuck")
        if self.bootloader is not None:
            cmd += ["--bootloader", str(self.bootloader)]
        if self.firmware is not None:
            cmd.append(str(self.firmware))
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True, start_new_session=True)
        port = self._read_port()
        self.port = port
        return port

    def _read_port(self) -> str:
        result: list[str] = []

        def reader():
            for line in self.proc.stdout:
                if line.startswith("PTY "):
                    result.append(line.split(None, 1)[1].strip())
                    return

        th = threading.Thread(target=reader, daemon=True)
        th.start()
        th.join(self.start_timeout)
        if not result:
            proc = self.proc
            if proc.poll() is None:
                proc.kill()
            err = proc.stderr.read() if proc.stderr else ""
            code = proc.wait()
            self.stop()
            msg = " ".join(err.split())[-500:].removeprefix("virtual_arduino: ")
            if code == 2 and self.eeprom is not None and str(self.eeprom) in msg:
                raise EepromFileError(msg)      # the harness's own check of --eeprom
            raise VirtualArduinoError(f"{HARNESS}: did not report its pty within "
                                      f"{self.start_timeout} s: {msg}")
        return result[0]

    def pin_log(self) -> np.ndarray:
        """Pin edges logged so far (flushed every simulated millisecond)."""
        return read_pin_log(self.log_path)

    def stop(self) -> None:
        """Stop the harness (SIGTERM: it saves --eeprom, flushes the log and exits).

        When the EEPROM image could not be saved, ``save_error`` says why (see ``close``).
        """
        if self.proc is None:
            return
        killed = False
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
                killed = True
        err = ""
        if self.proc.stderr and self.proc.returncode is not None:
            try:
                err = self.proc.stderr.read()
            except (OSError, ValueError):
                err = ""
        if self.eeprom is not None and self.port is not None:
            if killed:
                self.save_error = (f"{self.eeprom}: the virtual Arduino did not stop within 5 s "
                                   "and was killed; the EEPROM settings of this run were not saved")
            elif self.proc.returncode == 1:
                lines = [ln.removeprefix("virtual_arduino: ") for ln in err.splitlines()
                         if "EEPROM" in ln]
                self.save_error = lines[-1] if lines else (
                    f"{self.eeprom}: the EEPROM image could not be saved")
        for stream in (self.proc.stdout, self.proc.stderr):
            if stream:
                stream.close()
        self.proc = None

    def close(self, check: bool = True) -> None:
        """Stop and remove the temp folder; with ``check``, raise EepromFileError when the
        EEPROM image could not be saved (the settings of this run are lost)."""
        self.stop()
        if self._own_dir:
            shutil.rmtree(self.workdir, ignore_errors=True)
        if check and self.save_error:
            err, self.save_error = self.save_error, None
            raise EepromFileError(err)

    def __enter__(self) -> "VirtualArduino":
        self.start()
        return self

    def __exit__(self, exc_type, *exc) -> None:
        self.close(check=exc_type is None)

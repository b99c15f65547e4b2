"""Flash the servo-rig firmware onto an Arduino Uno / Nano with avrdude.

``flash(port, board)`` builds ``firmware/build/rig_servo.hex`` if needed and runs
``avrdude -c arduino -p m328p -P PORT -b BAUD -U flash:w:HEX:i`` with the baud rate of the
board's bootloader: Uno (optiboot) 115200, Nano (old ATmegaBOOT) 57600.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

from evdnerf_ros.errors import EvdnerfError

BOARDS = {"uno": 115200, "nano": 57600}


class FlashError(EvdnerfError):
    """avrdude is missing, the port is missing, or avrdude failed."""


@dataclass(frozen=True)
class FlashResult:
    command: list[str]
    output: str
    hex_path: Path


def avrdude_command(port: str, board: str, hex_path, avrdude: str = "avrdude") -> list[str]:
    if board not in BOARDS:
        raise FlashError(f"unknown board {board!r}: choose one of {', '.join(BOARDS)}")
    return [avrdude, "-c", "arduino", "-p", "m328p", "-P", str(port), "-b", str(BOARDS[board]),
            "-U", f"flash:w:{hex_path}:i"]


def flash(port: str, board: str = "uno", hex_path: str | os.PathLike | None = None, *,
          avrdude: str = "avrdude", timeout: float = 120.0) -> FlashResult:
    """Write the firmware through the board's serial bootloader; raise FlashError on failure."""
    if board not in BOARDS:
        raise FlashError(f"unknown board {board!r}: choose one of {', '.join(BOARDS)}")
    exe = shutil.which(avrdude)
    if exe is None:
        raise FlashError(f"{avrdude}: not found; install it: apt-get install -y avrdude "
                         "(Debian package avrdude)")
    if hex_path is None:
        from .virtual_arduino import FIRMWARE_HEX, build

        build()
        hex_path = FIRMWARE_HEX
    hex_path = Path(hex_path)
    if not hex_path.is_file():
        raise FlashError(f"{hex_path}: firmware hex not found; build it with "
                         "`make -C firmware` or leave out --hex")
    if not Path(port).exists():
        raise FlashError(f"{port}: no such serial port; plug the board in and check "
                         "`ls /dev/ttyACM* /dev/ttyUSB*`")
    cmd = avrdude_command(port, board, hex_path, exe)
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        raise FlashError(f"{port}: avrdude did not finish within {timeout:.0f} s") from None
    out = (res.stdout or "") + (res.stderr or "")
    if res.returncode != 0:
        tail = " | ".join(line.strip() for line in out.strip().splitlines()[-4:])
        hint = (" (Uno: --board uno, 115200 baud; old Nano bootloader: --board nano, 57600)"
                if "not in sync" in out or "not responding" in out else "")
        raise FlashError(f"{port}: avrdude failed (exit {res.returncode}): {tail}{hint}")
    return FlashResult(cmd, out, hex_path)

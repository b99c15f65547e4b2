"""Fault injection for the rig commands (`evdnerf servo`, the virtual Arduino's EEPROM file).

Every bad input ends in exit status 2 and one line `evdnerf: error: ...` naming the argument,
port or file at fault, before anything is sent to a device; nothing is overwritten.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from evdnerf_ros.cli import main


def run_cli(argv, capsys):
    """(exit status, stderr) of `evdnerf ARGV`, argparse's own exits included."""
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    out = capsys.readouterr()
    return code, out.err


def assert_one_line_error(code, err, *names):
    assert code == 2, err
    assert err.count("\n") == 1 and err.startswith("evdnerf: error: "), err
    assert "Traceback" not in err
    for name in names:
        assert name in err, (name, err)


@pytest.fixture
def no_device(monkeypatch):
    """Fail the test if a range error ever got as far as a port or a virtual Arduino."""
    from rig import servo, virtual_arduino

    def refuse(*a, **k):
        raise AssertionError("a device was contacted before the arguments were checked")

    monkeypatch.setattr(servo.ServoClient, "open", refuse)
    monkeypatch.setattr(virtual_arduino.VirtualArduino, "start", refuse)


# --------------------------------------------------------------------------- servo arguments

BAD_SERVO_ARGS = [
    # (arguments after `servo --virtual`, words the error must name)
    (["move", "nan", "500"], ["servo move ANGLE", "finite"]),
    (["move", "inf", "500"], ["servo move ANGLE"]),
    (["move", "--", "-inf", "500"], ["servo move ANGLE"]),
    (["move", "1e30", "500"], ["servo move ANGLE", "180"]),
    (["move", "--", "-5", "500"], ["servo move ANGLE", ">= 0"]),
    (["move", "90.0005", "500"], ["servo move ANGLE", "3 decimals"]),
    (["move", "90", "0"], ["servo move MS", "1", "65535"]),
    (["move", "90", "--", "-100"], ["servo move MS"]),
    (["move", "90", "70000"], ["servo move MS", "65535"]),
    (["move", "90", "nan"], ["ms", "nan"]),                  # argparse: not a whole number
    (["move", "ninety", "500"], ["angle", "ninety"]),
    (["turn", "181", "500"], ["servo turn ANGLE"]),
    (["turn", "90", "1e3"], ["ms", "1e3"]),
    (["home", "0"], ["servo home MS"]),
    (["home", "99999999999999999999"], ["servo home MS"]),
    (["ping", "-n", "0"], ["--count"]),
    (["ping", "-n", "100000000"], ["--count"]),
    (["set-limits", "nan", "180", "600", "1000", "2000"], ["MIN_DEG"]),
    (["set-limits", "0", "inf", "600", "1000", "2000"], ["MAX_DEG"]),
    (["set-limits", "10", "5", "600", "1000", "2000"], ["MIN_DEG", "below MAX_DEG"]),
    (["set-limits", "0", "180", "0", "1000", "2000"], ["MAX_SPEED_DPS", "6000"]),
    (["set-limits", "0", "180", "1e30", "1000", "2000"], ["MAX_SPEED_DPS"]),
    (["set-limits", "0", "180", "600.5", "1000", "2000"], ["MAX_SPEED_DPS", "whole number"]),
    (["set-limits", "0", "180", "600", "300", "2000"], ["PULSE_MIN_US", "400"]),
    (["set-limits", "0", "180", "600", "1000", "nan"], ["PULSE_MAX_US"]),
    (["set-limits", "0", "180", "600", "2000", "1000"], ["PULSE_MIN_US", "below PULSE_MAX_US"]),
    (["set-profile", "90", "120"], ["set-profile", "pairs"]),
    (["set-profile", "nan", "120", "200"], ["set-profile start angle"]),
    (["set-profile", "90", "181", "200"], ["segment 1 angle"]),
    (["set-profile", "90", "120", "nan"], ["segment 1 duration"]),
    (["set-profile", "90", "120", "inf"], ["segment 1 duration"]),
    (["set-profile", "90", "120", "1e30"], ["segment 1 duration"]),
    (["set-profile", "90", "120", "200", "100", "--", "-5"], ["segment 2 duration"]),
    (["set-profile", "90", "120", "200.5"], ["segment 1 duration", "whole number"]),
    (["set-profile", "90"] + ["100", "100"] * 9, ["9 segments", "1..8"]),
]


@pytest.mark.parametrize("args, names", BAD_SERVO_ARGS,
                         ids=[" ".join(a) for a, _ in BAD_SERVO_ARGS])
def test_bad_servo_arguments_are_one_line_errors(args, names, capsys, no_device):
    code, err = run_cli(["servo", "--virtual"] + args, capsys)
    assert_one_line_error(code, err, *names)


@pytest.mark.parametrize("timeout", ["nan", "inf", "0", "-1", "1e30"])
def test_bad_timeout(timeout, capsys, no_device):
    code, err = run_cli(["servo", "--virtual", f"--timeout={timeout}", "hello"], capsys)
    assert_one_line_error(code, err, "--timeout")


def test_eeprom_needs_virtual(tmp_path, capsys, no_device):
    code, err = run_cli(["servo", "--port", "/dev/ttyACM0", "--eeprom", str(tmp_path / "e"),
                         "hello"], capsys)
    assert_one_line_error(code, err, "--eeprom", "--virtual")


def test_an_eight_segment_profile_is_accepted_by_the_checks(capsys):
    import argparse

    from rig.cli import _check_servo_args

    v = [90.0] + [100.125, 65535.0] * 8
    args = argparse.Namespace(action="set-profile", values=v, timeout=1.0, eeprom=None,
                              virtual=True)
    _check_servo_args(args)
    assert len(args.profile.segments) == 8


# --------------------------------------------------------------------------- ports

def test_bad_ports_name_the_port(tmp_path, capsys):
    regular = tmp_path / "notaport"
    regular.write_text("x")
    cases = {str(tmp_path / "ttyACM9"): "no such serial port",
             str(tmp_path): "not a serial device (a folder)",
             str(regular): "not a serial device (a regular file)",
             "/dev/null": "cannot open the servo port"}      # a character device, not a tty
    for port, what in cases.items():
        t0 = time.monotonic()
        code, err = run_cli(["servo", "--port", port, "hello"], capsys)
        assert_one_line_error(code, err, port, what)
        assert time.monotonic() - t0 < 5


@pytest.mark.skipif(os.geteuid() == 0, reason="root opens any port whatever its permissions")
def test_port_without_permission(tmp_path, capsys):
    import pty

    master, slave = pty.openpty()
    try:
        name = os.ttyname(slave)
        os.chmod(name, 0o600)
        os.chown(name, 0, 0)
        code, err = run_cli(["servo", "--port", name, "hello"], capsys)
        assert_one_line_error(code, err, name, "permission denied")
    finally:
        os.close(master)
        os.close(slave)


# --------------------------------------------------------------------------- EEPROM image file

def _bad_eeprom_paths(tmp_path):
    short = tmp_path / "short.bin"
    short.write_bytes(b"\x01" * 10)
    long = tmp_path / "long.bin"
    long.write_bytes(b"\x02" * 2048)
    empty = tmp_path / "empty.bin"
    empty.write_bytes(b"")
    folder = tmp_path / "folder.bin"
    folder.mkdir()
    parent_is_file = tmp_path / "short.bin" / "ee.bin"
    return {tmp_path / "missing" / "ee.bin": "does not exist",
            folder: "not a regular file",
            parent_is_file: "does not exist",
            short: "10 bytes, expected 1024",
            long: "2048 bytes, expected 1024",
            empty: "0 bytes, expected 1024"}


def test_bad_eeprom_files_are_refused_before_start(tmp_path, capsys, monkeypatch):
    from rig import virtual_arduino as va_mod

    monkeypatch.setattr(va_mod, "build", lambda: pytest.fail("started despite a bad --eeprom"))
    for path, what in _bad_eeprom_paths(tmp_path).items():
        before = path.read_bytes() if path.is_file() else None
        code, err = run_cli(["servo", "--virtual", "--eeprom", str(path), "hello"], capsys)
        assert_one_line_error(code, err, str(path), what)
        if before is not None:
            assert path.read_bytes() == before          # a corrupt image is never overwritten
    from evdnerf_ros.errors import InputError

    assert issubclass(va_mod.EepromFileError, InputError)


def test_harness_refuses_bad_eeprom_files_itself(built, tmp_path):
    """The harness binary checks too (exit 2, path named), for users who run it directly."""
    from rig import virtual_arduino as va_mod

    for path, what in _bad_eeprom_paths(tmp_path).items():
        before = path.read_bytes() if path.is_file() else None
        res = subprocess.run([str(va_mod.HARNESS), "--eeprom", str(path),
                              str(va_mod.FIRMWARE_HEX)], capture_output=True, text=True,
                             timeout=10)
        assert res.returncode == 2 and str(path) in res.stderr and what in res.stderr, res
        assert "PTY" not in res.stdout
        if before is not None:
            assert path.read_bytes() == before


def test_harness_check_reaches_the_caller_as_an_input_error(built, tmp_path, monkeypatch):
    """A file that turns bad between the Python check and the harness start is still named."""
    from rig import virtual_arduino as va_mod

    bad = tmp_path / "short.bin"
    bad.write_bytes(b"\x00" * 7)
    monkeypatch.setattr(va_mod, "check_eeprom_file", lambda p: p)
    v = va_mod.VirtualArduino(eeprom=bad, workdir=tmp_path / "w")
    with pytest.raises(va_mod.EepromFileError, match="short.bin: EEPROM image is 7 bytes"):
        v.start()
    v.close()


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes anywhere whatever the permissions")
def test_unwritable_eeprom_file_and_folder(tmp_path, capsys):
    ro_file = tmp_path / "ro.bin"
    ro_file.write_bytes(b"\xff" * 1024)
    ro_file.chmod(0o444)
    ro_dir = tmp_path / "ro"
    ro_dir.mkdir()
    ro_dir.chmod(0o555)
    try:
        for path, what in ((ro_file, "not readable and writable"),
                           (ro_dir / "ee.bin", "not writable")):
            code, err = run_cli(["servo", "--virtual", "--eeprom", str(path), "hello"], capsys)
            assert_one_line_error(code, err, str(path), what)
    finally:
        ro_dir.chmod(0o755)


def test_eeprom_that_cannot_be_saved_is_reported(built, tmp_path):
    """The folder vanishes while the chip runs: stopping says the settings were not saved."""
    import shutil

    from rig import virtual_arduino as va_mod

    folder = tmp_path / "kept"
    folder.mkdir()
    v = va_mod.VirtualArduino(eeprom=folder / "ee.bin", workdir=tmp_path / "w")
    v.start()
    shutil.rmtree(folder)
    with pytest.raises(va_mod.EepromFileError, match=r"kept/ee\.bin: cannot save the EEPROM"):
        v.close()


def test_harness_saves_and_exits_when_its_parent_is_killed(built, tmp_path):
    """SIGKILL of the command that started the virtual Arduino: no orphan keeps running, and
    the EEPROM image is still written."""
    ee = tmp_path / "ee.bin"
    code = ("import sys, time\n"
            "from rig.virtual_arduino import VirtualArduino\n"
            f"v = VirtualArduino(eeprom={str(ee)!r}, workdir={str(tmp_path / 'w')!r})\n"
            "v.start()\n"
            "print(v.proc.pid, flush=True)\n"
            "time.sleep(60)\n")
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    child = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                             cwd=root)
    try:
        harness_pid = int(child.stdout.readline())
        child.kill()
        child.wait()
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and _alive(harness_pid):
            time.sleep(0.05)
        assert not _alive(harness_pid)
        assert ee.stat().st_size == 1024
    finally:
        if child.poll() is None:
            child.kill()
        child.stdout.close()


def _alive(pid: int) -> bool:
    """Running (a zombie left to an init that does not reap counts as gone)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False

"""The servo-rig firmware, run for real in simavr (the virtual Arduino).

Skipped, naming the Debian packages, only when avr-gcc / avr-libc / simavr headers are absent.
Every test starts its own harness in its own temp folder (tests run in parallel).
"""

from __future__ import annotations

import re
import shutil
import subprocess
import time

import numpy as np
import pytest

from evdnerf_ros.geometry.servo_profile import DEFAULT_RUN, RunProfile, move_command_mdeg
from rig import virtual_arduino as va_mod

FRAME_NS = 20_000_000


@pytest.fixture
def va(built, tmp_path):
    v = va_mod.VirtualArduino(workdir=tmp_path, eeprom=tmp_path / "eeprom.bin")
    v.start()
    yield v
    v.close()


@pytest.fixture
def client(va):
    from rig.servo import ServoClient

    with ServoClient(va.port, timeout=2.0) as c:
        yield c


def wait_log(va, predicate, timeout=10.0):
    """Pin log once predicate(log) holds (the harness flushes every simulated ms)."""
    deadline = time.monotonic() + timeout
    while True:
        log = va.pin_log()
        if predicate(log) or time.monotonic() > deadline:
            return log
        time.sleep(0.05)


def expected_width_us(mdeg, pmin=1000, pmax=2000):
    return pmin + mdeg * (pmax - pmin) / 180000


def raw_exchange(port, payload: bytes, wait=0.6) -> list[str]:
    import serial

    with serial.Serial(port, 115200, timeout=0.05) as s:
        s.write(payload)
        s.flush()
        deadline, buf = time.monotonic() + wait, b""
        while time.monotonic() < deadline:
            buf += s.read(s.in_waiting or 1)
    return [ln for ln in buf.decode("ascii", "replace").splitlines() if ln]


# --------------------------------------------------------------------------- build, C vs Python

def test_firmware_builds(built, tmp_path):
    res = subprocess.run(["make", "-C", str(va_mod.FIRMWARE_DIR), f"BUILD={tmp_path}"],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    hexfile = tmp_path / "rig_servo.hex"
    lines = hexfile.read_text().split()
    assert lines[-1] == ":00000001FF" and all(ln.startswith(":") for ln in lines)
    for ln in lines:   # every Intel-hex record checksums to zero
        assert sum(bytes.fromhex(ln[1:])) % 256 == 0
    size = subprocess.run(["avr-size", str(tmp_path / "rig_servo.elf")], capture_output=True,
                          text=True).stdout.split("\n")[1].split()
    text, data, bss = map(int, size[:3])
    assert text + data < 30 * 1024            # leaves room for a 2 KiB bootloader
    assert data + bss < 1024                  # half of the 2 KiB SRAM stays for the stack
    assert (tmp_path / "virtual_arduino").exists()


def test_profile_core_matches_servo_profile_module(built, tmp_path):
    """firmware/core/profile.c, compiled for the host, equals servo_profile.py value by value."""
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no host C compiler (Debian package gcc)")
    driver = tmp_path / "drv.c"
    driver.write_text(r'''
#include <stdio.h>
#include "profile.h"
int main(void) {
  unsigned long e, d; long a0, a1; int m, pmin, pmax;
  while (scanf("%lu %lu %ld %ld %d %d %d", &e, &d, &a0, &a1, &m, &pmin, &pmax) == 7)
    printf("%ld %u\n", (long)rig_move_command_mdeg(e, d, a0, a1),
           (unsigned)rig_pulse_ticks(m, pmin, pmax));
  return 0;
}''')
    exe = tmp_path / "drv"
    subprocess.run([cc, "-O2", "-I", str(va_mod.FIRMWARE_DIR / "core"), "-o", str(exe),
                    str(driver), str(va_mod.FIRMWARE_DIR / "core" / "profile.c")], check=True)
    rng = np.random.default_rng(6)
    cases = []
    for _ in range(4000):
        d = int(rng.integers(1, 65536)) * 1000
        e = int(rng.integers(0, d + 2000))
        a0, a1 = (int(x) for x in rng.integers(0, 180001, 2))
        m = int(rng.integers(0, 180001))
        pmin = int(rng.integers(400, 1500))
        pmax = int(rng.integers(pmin + 1, 2601))
        cases.append((e, d, a0, a1, m, pmin, pmax))
    cases += [(0, 1000, 0, 180000, 0, 1000, 2000), (1000, 1000, 0, 180000, 180000, 1000, 2000),
              (999, 1000, 180000, 0, 90000, 544, 2400), (1, 65535000, 0, 180000, 1, 1000, 2000)]
    out = subprocess.run([str(exe)], input="\n".join(" ".join(map(str, c)) for c in cases),
                         capture_output=True, text=True, check=True).stdout.split("\n")
    for c, line in zip(cases, out):
        e, d, a0, a1, m, pmin, pmax = c
        cmd, ticks = map(int, line.split())
        assert cmd == move_command_mdeg(e, d, a0, a1), c
        exact_ticks = 2 * pmin + m * 2 * (pmax - pmin) / 180000
        assert abs(ticks - exact_ticks) <= 0.5 + 1e-9, c


# --------------------------------------------------------------------------- protocol

def test_hello_and_ping(client):
    assert client.hello["proto"] == "1" and client.hello["fw"] == "1.0.0"
    assert client.hello["frame_us"] == "20000"
    r = client.command("PING tok42")
    assert r.words[:2] == ["OK", "PONG"] and r.words[3] == "TOK42"
    d1, _, _ = client.ping()
    d2, _, _ = client.ping()
    assert d2 > d1 > 0


def test_move_timing_done_minus_start(client):
    for angle, ms in ((130, 500), (60, 730), (61.5, 20)):
        m = client.move(angle, ms)
        assert m.end.kind == "DONE"
        assert abs(m.duration_us - ms * 1000) <= 25_000, (angle, ms, m)
        assert client.status()["servo_deg"] == angle


def _motion_pulses(log, t_trig, duration_ns):
    servo = va_mod.pulses(log, va_mod.PIN_SERVO)
    return [p for p in servo if t_trig - 1000 <= p.start_ns <= t_trig + duration_ns + 2 * FRAME_NS]


def test_pulse_widths_follow_the_run_profile(va, client):
    client.run()
    log = wait_log(va, lambda lg: len(va_mod.pulses(lg, va_mod.PIN_TRIGGER)) >= 1)
    trig = va_mod.pulses(log, va_mod.PIN_TRIGGER)
    assert len(trig) == 1
    t0 = trig[0].start_ns
    seen = _motion_pulses(log, t0, DEFAULT_RUN.duration_ns)
    assert len(seen) >= DEFAULT_RUN.duration_ns // FRAME_NS + 1
    errs = []
    for p in seen:
        k = round((p.start_ns - t0) / FRAME_NS)
        assert abs(p.start_ns - t0 - k * FRAME_NS) < 5_000          # frames every 20 ms
        want = expected_width_us(DEFAULT_RUN.command_mdeg(k * FRAME_NS))
        errs.append(p.width_ns / 1000 - want)
    errs = np.abs(errs)
    assert errs.max() <= 10.0, errs.max()
    # the swing reaches both extremes: 135 deg -> 1750 us, 45 deg -> 1250 us
    widths = np.array([p.width_ns for p in seen]) / 1000
    assert widths.max() > 1740 and widths.min() < 1260
    # before the motion the servo held the start angle (90 deg = 1500 us)
    before = [p for p in va_mod.pulses(log, va_mod.PIN_SERVO) if p.start_ns < t0]
    assert before and all(abs(p.width_ns / 1000 - 1500) <= 10 for p in before)


def test_pulse_range_is_configurable_and_move_profile_matches(va, client):
    from rig.servo import Limits

    client.set_limits(Limits(0, 180, 900, 800, 2200))
    client.move(30, 400)
    log = wait_log(va, lambda lg: len(va_mod.pulses(lg, va_mod.PIN_TRIGGER)) >= 1)
    t0 = va_mod.pulses(log, va_mod.PIN_TRIGGER)[0].start_ns
    seen = _motion_pulses(log, t0, 400 * 1_000_000)
    assert len(seen) >= 21
    for p in seen:
        k = round((p.start_ns - t0) / FRAME_NS)
        cmd = RunProfile(90.0, ((30.0, 400),)).command_mdeg(k * FRAME_NS)
        assert abs(p.width_ns / 1000 - expected_width_us(cmd, 800, 2200)) <= 10.0


def test_trigger_coincides_with_start(va, client):
    m1 = client.move(100, 100)
    m2 = client.move(80, 100)
    log = wait_log(va, lambda lg: len(va_mod.pulses(lg, va_mod.PIN_TRIGGER)) >= 2)
    trig = va_mod.pulses(log, va_mod.PIN_TRIGGER)
    assert len(trig) == 2
    servo_rises = {p.start_ns for p in va_mod.pulses(log, va_mod.PIN_SERVO)}
    for t in trig:
        assert t.start_ns in servo_rises                      # same cycle as the servo frame
        assert abs(t.width_ns - 1_000_000) <= 10_000          # 1 ms trigger pulse
    # device START times and simulated trigger times differ by one constant (< 1 us)
    d_dev = (m2.start.device_us - m1.start.device_us) * 1000
    d_sim = trig[1].start_ns - trig[0].start_ns
    assert abs(d_dev - d_sim) < 1_000
    # and the trigger sits at the device time START reports, up to the boot offset (<1 ms)
    assert 0 <= trig[0].start_ns - m1.start.device_us * 1000 < 1_000_000


def test_malformed_and_overlong_lines_never_move(va, client):
    bad = {
        "FLY 90": "UNKNOWN_COMMAND", "MOVE": "BAD_ARGUMENT", "MOVE abc 100": "BAD_ARGUMENT",
        "MOVE 90.1234 100": "BAD_ARGUMENT", "MOVE 90 0": "BAD_ARGUMENT",
        "MOVE 90 70000": "BAD_ARGUMENT", "MOVE 90 100 7": "BAD_ARGUMENT",
        "SET LIMITS 1 2": "BAD_ARGUMENT", "RUN now": "BAD_ARGUMENT", "GET FOO": "BAD_ARGUMENT",
        "SET PROFILE 90 100": "BAD_ARGUMENT",
    }
    from rig.servo import ServoCommandError

    for line, code in bad.items():
        with pytest.raises(ServoCommandError) as exc:
            client.command(line, retries=0)
        assert exc.value.code == code, line
    client.close()
    port = va.port
    lines = raw_exchange(port, b"M" * 1024 + b"OVE 100 100\n" + b"MOVE 100 \x01100\n"
                         + bytes(range(128, 256)) + b"\n" + b"\xff\x00garbage\n" + b"PING\n")
    assert lines[0].startswith("ERR LINE_TOO_LONG")
    assert lines[1].startswith("ERR BAD_CHARACTER")
    assert lines[2].startswith("ERR BAD_CHARACTER") and lines[3].startswith("ERR BAD_CHARACTER")
    assert lines[4].startswith("OK PONG")
    from rig.servo import ServoClient

    with ServoClient(port) as c:
        assert c.status() == {"servo_deg": 90.0, "turntable_deg": 90.0, "servo": "IDLE",
                              "turntable": "IDLE"}
    log = va.pin_log()
    assert len(va_mod.pulses(log, va_mod.PIN_TRIGGER)) == 0               # nothing moved
    assert all(abs(p.width_ns / 1000 - 1500) <= 10 for p in va_mod.pulses(log, va_mod.PIN_SERVO))


def test_out_of_range_and_too_fast_are_refused(client):
    from rig.servo import Limits, ServoCommandError

    def code(line):
        with pytest.raises(ServoCommandError) as exc:
            client.command(line, retries=0)
        return exc.value.code

    assert code("MOVE 180.001 1000") == "OUT_OF_RANGE"
    assert code("MOVE -5 1000") == "OUT_OF_RANGE"
    assert code("TURN 181 1000") == "OUT_OF_RANGE"
    assert code("SET LIMITS 10 5 100 1000 2000") == "OUT_OF_RANGE"
    assert code("SET LIMITS 0 180 100 300 2000") == "OUT_OF_RANGE"
    client.set_limits(Limits(20, 160, 100, 1000, 2000))
    assert code("MOVE 10 1000") == "OUT_OF_RANGE"
    # 90 -> 150 deg: peak 1.875 * 60 / 1 s = 112.5 deg/s > 100
    assert code("MOVE 150 1000") == "TOO_FAST"
    assert code("RUN") == "PROFILE_LIMITS"        # the fork swing peaks at 337.5 deg/s
    m = client.move(150, 1200)                    # 93.75 deg/s: allowed
    assert m.end.kind == "DONE"
    assert code("RUN") == "NOT_HOME"


def test_commands_during_motion(va, client):
    from rig.servo import ServoCommandError

    client.set_profile(RunProfile(90.0, ((150.0, 2000), (90.0, 2000))))
    client.run(wait=False)
    ev = client.next_event(timeout=5)
    assert (ev.kind, ev.motion) == ("START", "RUN")
    for line, c in (("MOVE 100 500", "BUSY"), ("RUN", "BUSY"), ("HOME", "BUSY"),
                    ("SET LIMITS 0 180 600 1000 2000", "BUSY"),
                    ("SET PROFILE 90 100 500", "BUSY")):
        with pytest.raises(ServoCommandError) as exc:
            client.command(line, retries=0)
        assert exc.value.code == c
    assert client.status()["servo"] == "RUN"
    client.ping()
    client.stop()
    ev = client.next_event(timeout=5)
    assert (ev.kind, ev.motion) == ("STOPPED", "RUN")
    held = float(ev.words[0])
    assert 90 < held < 150
    st = client.status()
    assert st["servo"] == "IDLE" and st["servo_deg"] == held
    t_stop = va.pin_log()["t_ns"].max()
    client.ping()
    time.sleep(0.3)
    later = [p for p in va_mod.pulses(va.pin_log(), va_mod.PIN_SERVO) if p.start_ns > t_stop]
    assert len(later) >= 3
    assert all(abs(p.width_ns / 1000 - expected_width_us(held * 1000)) <= 10 for p in later)
    assert client.move(90, 1000).end.kind == "DONE"     # answers and moves again


def test_host_disappearing_mid_motion(va, client):
    from rig.servo import ServoClient

    port = va.port
    client.close()
    import serial

    with serial.Serial(port, 115200, timeout=0.05) as s:
        s.write(b"RUN\n")
        s.flush()
        time.sleep(0.05)
    # the host is gone: the motion completes on its own
    log = wait_log(va, lambda lg: len(va_mod.pulses(lg, va_mod.PIN_TRIGGER)) >= 1 and
                   lg["t_ns"].max() > va_mod.pulses(lg, va_mod.PIN_TRIGGER)[0].start_ns
                   + DEFAULT_RUN.duration_ns + 3 * FRAME_NS)
    t0 = va_mod.pulses(log, va_mod.PIN_TRIGGER)[0].start_ns
    seen = _motion_pulses(log, t0, DEFAULT_RUN.duration_ns)
    for p in seen:
        k = round((p.start_ns - t0) / FRAME_NS)
        want = expected_width_us(DEFAULT_RUN.command_mdeg(k * FRAME_NS))
        assert abs(p.width_ns / 1000 - want) <= 10
    with ServoClient(port) as c:            # a new host connects: it answers, idle at home
        st = c.status()
        assert st["servo"] == "IDLE" and st["servo_deg"] == 90.0
        assert c.run().end.kind == "DONE"


def test_eeprom_survives_watchdog_reset_and_power_cycle(built, tmp_path):
    from rig.servo import Limits, ServoClient

    eeprom = tmp_path / "ee.bin"
    prof = RunProfile(80.0, ((100.5, 300), (60.25, 400), (80.0, 300)))
    lim = Limits(5, 175, 700, 900, 2100)
    with va_mod.VirtualArduino(workdir=tmp_path / "a", eeprom=eeprom) as v, \
            ServoClient(v.port) as c:
        assert c.get_profile() == DEFAULT_RUN                  # erased EEPROM: defaults
        assert c.set_profile(prof) == prof
        assert c.set_limits(lim) == lim
        c.drain_events()
        c.command("REBOOT", retries=0)                         # watchdog reset
        boot = c.next_event(timeout=5)
        assert boot.kind == "BOOT" and "reset=8" in boot.words  # MCUSR.WDRF
        assert c.get_profile() == prof and c.get_limits() == lim
        assert c.status()["servo_deg"] == 80.0                 # powers up at the profile start
    assert eeprom.stat().st_size == 1024
    with va_mod.VirtualArduino(workdir=tmp_path / "b", eeprom=eeprom) as v, \
            ServoClient(v.port) as c:                          # power cycle
        assert c.get_profile() == prof and c.get_limits() == lim
        m = c.run()
        assert m.duration_us == 1_000_000
        c.command("FACTORY")
        assert c.get_profile() == DEFAULT_RUN


def test_turntable_channel(va, client):
    m = client.turn(150, 300)
    assert m.end.kind == "DONE" and abs(m.duration_us - 300_000) <= 25_000
    log = wait_log(va, lambda lg: True)
    turn = va_mod.pulses(log, va_mod.PIN_TURNTABLE)
    assert abs(turn[0].width_ns / 1000 - 1500) <= 10
    assert abs(turn[-1].width_ns / 1000 - expected_width_us(150000)) <= 10
    assert not va_mod.pulses(log, va_mod.PIN_TRIGGER)        # the trigger marks servo motions


# --------------------------------------------------------------------------- flashing

def test_flash_with_avrdude_into_the_virtual_arduino(built, tmp_path):
    if "avrdude" in va_mod.missing_tools():
        pytest.skip("flashing test needs the Debian package avrdude")
    if not va_mod.ATMEGABOOT_HEX.exists():
        pytest.skip(f"flashing test needs the Debian package {va_mod.BOOTLOADER_PACKAGE} "
                    "(the ATmegaBOOT bootloader)")
    from evdnerf_ros.cli import main
    from rig.servo import ServoClient

    # the chip holds only the bootloader (flash erased), paced to real time for avrdude
    with va_mod.VirtualArduino(firmware=None, bootloader=va_mod.ATMEGABOOT_HEX, pace=True,
                               workdir=tmp_path) as v:
        assert main(["flash", "--port", v.port, "--board", "nano"]) == 0
        with ServoClient(v.port) as c:
            assert c.hello["proto"] == "1"
            assert c.move(100, 200).end.kind == "DONE"


def test_flash_errors(tmp_path, monkeypatch, capsys):
    from evdnerf_ros.cli import main

    assert main(["flash", "--port", str(tmp_path / "ttyNOPE"), "--hex",
                 str(va_mod.FIRMWARE_DIR / "Makefile")]) == 2
    err = capsys.readouterr().err
    assert "ttyNOPE: no such serial port" in err and err.count("\n") == 1
    monkeypatch.setenv("PATH", str(tmp_path))
    assert main(["flash", "--port", "/dev/null"]) == 2
    err = capsys.readouterr().err
    assert re.search(r"avrdude: not found; install it: apt-get install -y avrdude", err)


def test_arduino_sketch_compiles_against_the_arduino_core(built, tmp_path):
    core = va_mod.ATMEGABOOT_HEX.parents[2]          # .../hardware/arduino/avr
    if not (core / "cores" / "arduino" / "Arduino.h").exists():
        pytest.skip(f"needs the Debian package {va_mod.BOOTLOADER_PACKAGE} (Arduino core)")
    res = subprocess.run(
        ["avr-g++", "-x", "c++", "-mmcu=atmega328p", "-DF_CPU=16000000UL", "-DARDUINO=10807",
         "-DARDUINO_ARCH_AVR", "-DDECIMAL_DIG=__DECIMAL_DIG__", "-Os", "-include", "Arduino.h",
         f"-I{core / 'cores' / 'arduino'}", f"-I{core / 'variants' / 'standard'}", "-c",
         str(va_mod.FIRMWARE_DIR / "rig_servo" / "rig_servo.ino"), "-o", str(tmp_path / "s.o")],
        capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    syms = subprocess.run(["avr-nm", str(tmp_path / "s.o")], capture_output=True,
                          text=True).stdout
    # the sketch calls the C core unmangled, and the core is reachable through src/
    assert " U rig_setup" in syms and " U rig_loop" in syms
    assert (va_mod.FIRMWARE_DIR / "rig_servo" / "src" / "rig.c").exists()


# --------------------------------------------------------------------------- tags on every reply

def raw_replies(port, lines: list[bytes], per_line=0.25) -> list[list[str]]:
    """Send each line alone and collect the lines that come back before the next is sent."""
    import serial

    out, buf = [], b""
    with serial.Serial(port, 115200, timeout=0.02) as s:
        for ln in lines:
            s.write(ln)
            s.flush()
            deadline = time.monotonic() + per_line
            while time.monotonic() < deadline:
                buf += s.read(s.in_waiting or 1)
            *done, buf = buf.split(b"\n")            # a report may be cut mid-line
            out.append([x for x in (d.decode("ascii", "replace") for d in done)
                        if x and not x.startswith(("BOOT", "START", "DONE", "STOPPED"))])
    return out


def test_every_error_reply_carries_its_tag(va, client):
    """Each error path answers `@<tag> ERR <CODE>`: line-level errors included."""
    client.close()
    cases = [
        (b"@1 " + b"X" * 300 + b"\n", "LINE_TOO_LONG"),
        (b"@2 FLY 90\n", "UNKNOWN_COMMAND"),
        (b"@3 MOVE abc 100\n", "BAD_ARGUMENT"),           # bad number
        (b"@4 MOVE 90.1234 100\n", "BAD_ARGUMENT"),
        (b"@5 MOVE 181 100\n", "OUT_OF_RANGE"),
        (b"@6 MOVE 90\n", "BAD_ARGUMENT"),                # wrong argument count
        (b"@7 SET PROFILE 90 100\n", "BAD_ARGUMENT"),
        (b"@8 SET LIMITS 10 5 100 1000 2000\n", "OUT_OF_RANGE"),
        (b"@9 MOVE 179 1\n", "TOO_FAST"),
        (b"@10 PING" + b" A" * 30 + b"\n", "BAD_ARGUMENT"),  # too many arguments
        (b"@11 PING \x01\n", "BAD_CHARACTER"),
        (b"@12 PING \xff\n", "BAD_CHARACTER"),
        (b"@13\n", "BAD_ARGUMENT"),                       # empty command
        (b"@4294967295 GET FOO\n", "BAD_ARGUMENT"),       # the largest tag
        (b"@14 MOVE 120 200\n", "OK"),
        (b"@15 RUN\n", "NOT_HOME"),
        (b"@16 HOME 65535\n", "OK"),
        (b"@17 MOVE 100 500\n", "BUSY"),                   # HOME still runs
        (b"@18 SET PROFILE 90 100 500\n", "BUSY"),
        (b"@19 STOP\n", "OK"),
    ]
    replies = raw_replies(va.port, [ln for ln, _ in cases])
    for (line, code), got in zip(cases, replies):
        tag = line.split()[0].decode()
        assert len(got) == 1, (line, got)
        words = got[0].split()
        assert words[0] == tag, (line, got)
        if code == "OK":
            assert words[1] == "OK", (line, got)
        else:
            assert words[1:3] == ["ERR", code], (line, got)


def test_unreadable_tags_get_the_documented_untagged_reply(va, client):
    client.close()
    bad = [b"@x PING\n", b"@ PING\n", b"@4294967296 PING\n", b"@1\x012 PING\n", b"@-1 PING\n",
           b"@12abc PING\n"]
    for line, got in zip(bad, raw_replies(va.port, bad)):
        assert len(got) == 1 and got[0].startswith("ERR BAD_TAG "), (line, got)
    # the firmware moved on: a tagged line right after is answered normally
    got = raw_replies(va.port, [b"@77 PING\n"])
    assert got[0][0].startswith("@77 OK PONG ")


def test_client_gets_each_error_at_once_not_a_timeout(client):
    from rig.servo import ServoCommandError

    lines = {"PING " + "X" * 300: "LINE_TOO_LONG", "PING \x01": "BAD_CHARACTER",
             "FLY": "UNKNOWN_COMMAND", "MOVE nan 100": "BAD_ARGUMENT",
             "MOVE 90 0": "BAD_ARGUMENT", "TURN 200 100": "OUT_OF_RANGE",
             "PING " + "A " * 30: "BAD_ARGUMENT", "SET LIMITS 1": "BAD_ARGUMENT"}
    for line, code in lines.items():
        t0 = time.monotonic()
        with pytest.raises(ServoCommandError) as exc:
            client.command(line, retries=0)
        assert exc.value.code == code and not exc.value.untagged, line
        assert time.monotonic() - t0 < client.timeout / 2, line
        assert code in str(exc.value)


def test_client_recognises_untagged_errors_at_once(client, monkeypatch):
    """A tag the firmware cannot read (here: over 32 bits) is answered untagged; the client
    takes that as the answer to its command instead of waiting for a timeout."""
    import itertools

    from rig import servo as servo_mod
    from rig.servo import ServoCommandError

    monkeypatch.setattr(servo_mod, "TAG_MODULO", 1 << 40)
    client._seq = itertools.count(1 << 33)
    t0 = time.monotonic()
    with pytest.raises(ServoCommandError) as exc:
        client.command("PING", retries=2)
    assert exc.value.untagged and exc.value.code == "BAD_TAG"
    assert "garbled" in str(exc.value)
    assert time.monotonic() - t0 < client.timeout         # 3 attempts, none timed out
    monkeypatch.undo()
    client._seq = itertools.count(1)
    client.ping()


def test_eight_segment_profile_round_trip_and_run(client):
    """The protocol's maximum (8 segments) in its longest text form, with the longest tag."""
    import itertools

    longest = RunProfile(179.999, tuple((round(179.999 - k * 0.001, 3), 65535 - k)
                                         for k in range(8)))
    client._seq = itertools.count((1 << 32) - 3)          # @4294967293.. and wrapping to @0
    assert client.set_profile(longest) == longest
    assert client.get_profile() == longest
    assert client.get_profile() == longest                # tag wrapped past 2^32 - 1
    # an 8-segment profile that runs: 8 x 100 ms, peak speeds within 600 deg/s
    prof = RunProfile(90.0, tuple((90.0 + (20.125 if k % 2 == 0 else -10.5), 100)
                                  for k in range(8)))
    assert client.set_profile(prof) == prof
    assert client.get_profile() == prof
    client.home(500)
    m = client.run()
    assert m.end.kind == "DONE" and abs(m.duration_us - 800_000) <= 25_000


def test_flooded_receive_buffer_never_misattributes_a_reply(va, client):
    """40 long lines sent at once overflow the 64-byte receive buffer: every line still gets
    exactly one reply with its own tag (OK with its own token, or ERR RX_OVERFLOW)."""
    import serial

    client.close()
    tokens = {k: f"T{k}" + "Z" * 140 for k in range(40)}
    payload = b"".join(f"@{k} PING {tok}\n".encode() for k, tok in tokens.items())
    with serial.Serial(va.port, 115200, timeout=0.05) as s:
        s.write(payload)
        s.flush()
        deadline, buf = time.monotonic() + 10, b""
        while time.monotonic() < deadline and buf.count(b"\n") < 40:
            buf += s.read(s.in_waiting or 1)
    lines = [ln for ln in buf.decode().splitlines() if not ln.startswith("BOOT")]
    seen, overflowed = {}, 0
    for ln in lines:
        words = ln.split()
        if not words[0].startswith("@"):
            assert words[0] == "ERR", ln                 # the documented untagged form
            continue
        k = int(words[0][1:])
        assert k not in seen, ln
        seen[k] = words
        if words[1] == "OK":
            assert words[2] == "PONG" and words[4] == tokens[k].upper(), ln
        else:
            assert words[1:3] == ["ERR", "RX_OVERFLOW"], ln
            overflowed += 1
    assert len(lines) == 40
    assert overflowed >= 1                                # the path was exercised


def test_eeprom_write_failure_is_a_tagged_error(built, tmp_path):
    from rig.servo import Limits, ServoClient, ServoCommandError

    with va_mod.VirtualArduino(workdir=tmp_path, eeprom_stuck=True) as v, \
            ServoClient(v.port) as c:
        for call in (lambda: c.set_profile(RunProfile(80.0, ((100.0, 300),))),
                     lambda: c.set_limits(Limits(5, 175, 700, 900, 2100))):
            with pytest.raises(ServoCommandError) as exc:
                call()
            assert exc.value.code == "EEPROM" and not exc.value.untagged
        # RAM holds what the EEPROM holds (erased: the defaults), not the refused settings
        assert c.get_profile() == DEFAULT_RUN
        assert c.get_limits() == Limits(0, 180, 600, 1000, 2000)


def test_interrupt_handlers_stay_short(built, tmp_path):
    """The servo pulse edges are set in the Timer1 interrupt; the serial interrupts that can
    delay it must call no library routine (a '%' by a non-power of two is a ~15 us division)."""
    objdump = shutil.which("avr-objdump")
    if objdump is None:
        pytest.skip("needs avr-objdump (Debian package binutils-avr)")
    dis = subprocess.run([objdump, "-d", str(va_mod.BUILD_DIR / "rig_servo.elf")],
                         capture_output=True, text=True, check=True).stdout
    for vec in ("__vector_18", "__vector_19"):          # USART RX, USART data register empty
        body = dis.split(f"<{vec}>:", 1)[1].split("reti", 1)[0]
        assert "call" not in body, vec
        assert body.count("\n") < 60, vec

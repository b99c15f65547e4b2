"""rig.servo client logic against a scripted fake device, and `evdnerf servo --virtual`."""

from __future__ import annotations

import re
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from rig.servo import (ClockMap, ServoClient, ServoCommandError, ServoPortError,
                       ServoProtocolError, ServoTimeout)


class FakeDevice:
    """A serial-port stand-in: answers like the firmware; knobs to drop/delay/alter replies."""

    def __init__(self, proto=1, clock=lambda: time.monotonic_ns() // 1000, drop=0,
                 wrap_base=0):
        self.proto, self.clock, self.drop = proto, clock, drop
        self.wrap_base = wrap_base
        self.out = bytearray()
        self.cv = threading.Condition()
        self.commands: list[str] = []
        self.closed = False
        self.stale = []

    # serial.Serial surface used by ServoClient
    @property
    def in_waiting(self):
        return len(self.out)

    def read(self, n):
        with self.cv:
            if not self.out:
                self.cv.wait(0.02)
            data = bytes(self.out[:n])
            del self.out[:n]
            return data

    def flush(self):
        pass

    def close(self):
        self.closed = True

    def emit(self, line):
        with self.cv:
            self.out += (line + "\n").encode()
            self.cv.notify_all()

    def write(self, data):
        line = data.decode().strip()
        self.commands.append(line)
        tag, cmd = line.split(" ", 1)
        if self.drop:
            self.drop -= 1
            self.stale.append(tag)
            return len(data)
        for old in self.stale:          # late replies to dropped commands arrive now
            self.emit(f"{old} OK PONG 1")
        self.stale.clear()
        now = (self.clock() + self.wrap_base) % (1 << 32)
        if cmd == "PING":
            self.emit(f"{tag} OK PONG {now}")
        elif cmd == "HELLO":
            self.emit(f"{tag} OK HELLO rig_servo proto={self.proto} fw=9.9.9 frame_us=20000")
        elif cmd.startswith("MOVE"):
            self.emit(f"{tag} OK MOVE")
            self.emit(f"START MOVE {now}")
            self.emit(f"DONE MOVE {(now + 500_000) % (1 << 32)}")
        else:
            self.emit(f"{tag} ERR UNKNOWN_COMMAND nope")
        return len(data)


def client_for(dev, **kw):
    return ServoClient("fake", open_serial=lambda port, baud: dev, **kw)


def test_handshake_and_command_matching():
    dev = FakeDevice()
    with client_for(dev) as c:
        assert c.hello == {"proto": "1", "fw": "9.9.9", "frame_us": "20000"}
        with pytest.raises(ServoCommandError) as exc:
            c.command("FLY")
        assert exc.value.code == "UNKNOWN_COMMAND"
        m = c.move(12.5, 500)
        assert m.duration_us == 500_000
    assert dev.closed
    tags = [cmd.split()[0] for cmd in dev.commands]
    assert len(set(tags)) == len(tags) and all(t.startswith("@") for t in tags)
    assert "MOVE 12.5 500" in dev.commands[-1]


def test_version_mismatch_is_refused():
    with pytest.raises(ServoProtocolError, match="protocol 2, this client 1"):
        client_for(FakeDevice(proto=2)).open()


def test_retry_after_a_lost_reply_and_stale_replies_are_ignored():
    dev = FakeDevice()
    with client_for(dev, timeout=0.2, retries=2) as c:
        dev.drop = 1
        dev_us, _, _ = c.ping()            # first attempt unanswered, retried, answered
        assert dev_us != 1                 # the late "@n OK PONG 1" of attempt 1 was dropped
        assert dev.commands[-1].split()[0] != dev.commands[-2].split()[0]
        dev.drop = 10
        with pytest.raises(ServoTimeout, match="3 attempts"):
            c.ping()
        dev.drop = 0


def test_motion_commands_are_never_repeated():
    dev = FakeDevice()
    with client_for(dev, timeout=0.2, retries=3) as c:
        dev.drop = 1
        with pytest.raises(ServoTimeout, match="1 attempts"):
            c.move(10, 100)
        assert sum(cmd.split(" ", 1)[1].startswith("MOVE") for cmd in dev.commands) == 1


def test_clock_offset_and_drift_from_pings():
    # a device clock running 150 ppm fast with an offset, unwrapped across 2^32 us
    t0 = time.monotonic_ns()
    dev = FakeDevice(clock=lambda: int(((time.monotonic_ns() - t0) / 1000) * 1.000150),
                     wrap_base=(1 << 32) - 300_000)
    with client_for(dev) as c:
        for _ in range(80):     # 0.8 s of pings: a busy host's jitter still leaves the slope within 60 ppm
            c.ping()
            time.sleep(0.01)
        cm = c.sync_clock(pings=0)
        assert isinstance(cm, ClockMap) and cm.samples >= 20
        # host ns per device us: 1000 / 1.00015
        assert abs(cm.drift_ppm - (1000 / 1.00015 / 1000 - 1) * 1e6) < 60
        # the device wrapped past 2^32 during the pings and was unwrapped
        for _ in range(50):     # a ping whose round trip was not stretched by a busy host
            dev_now, s, r = c.ping()
            if r - s < 1_000_000:
                break
        assert dev_now > (1 << 32) - 300_000 + 300_000
        assert abs(c.device_to_host_ns(dev_now) - (s + r) / 2) < 2_000_000


def test_port_missing_is_a_typed_error(tmp_path):
    with pytest.raises(ServoPortError, match="ttyACM9: no such serial port"):
        ServoClient(str(tmp_path / "ttyACM9")).open()


def test_no_answer_names_the_fix():
    dev = FakeDevice(drop=10**6)
    with pytest.raises(ServoTimeout, match="evdnerf flash"):
        client_for(dev, boot_timeout=0.3, timeout=0.1).open()


# --------------------------------------------------------------------------- CLI (virtual)

def test_cli_servo_virtual(built, tmp_path, capsys):
    from evdnerf_ros.cli import main

    ee = str(tmp_path / "ee.bin")
    assert main(["servo", "--virtual", "--eeprom", ee, "hello"]) == 0
    assert '"proto": "1"' in capsys.readouterr().out
    assert main(["servo", "--virtual", "--eeprom", ee, "ping", "-n", "5"]) == 0
    out = capsys.readouterr().out
    assert out.count("round trip") == 5 and "drift" in out
    assert main(["servo", "--virtual", "--eeprom", ee, "set-profile", "90", "120", "200",
                 "90", "200"]) == 0
    capsys.readouterr()
    assert main(["servo", "--virtual", "--eeprom", ee, "get-profile"]) == 0
    assert '"segments": [[120.0, 200], [90.0, 200]]' in capsys.readouterr().out
    assert main(["servo", "--virtual", "--eeprom", ee, "run"]) == 0
    assert "(400.0 ms)" in capsys.readouterr().out
    assert main(["servo", "--virtual", "--eeprom", ee, "set-limits", "10", "170", "500",
                 "1000", "2000"]) == 0
    capsys.readouterr()
    assert main(["servo", "--virtual", "--eeprom", ee, "move", "175", "500"]) == 2
    err = capsys.readouterr().err
    assert "OUT_OF_RANGE" in err and err.count("\n") == 1
    assert main(["servo", "--virtual", "move", "120", "300"]) == 0
    assert "DONE" in capsys.readouterr().out


def test_library_never_imports_rig():
    root = Path(__file__).resolve().parents[1] / "evdnerf_ros"
    for f in root.rglob("*.py"):
        text = f.read_text()
        assert not re.search(r"^\s*(import rig\b|from rig\b)", text, re.M), f


def test_cli_finds_plugin_commands():
    from evdnerf_ros.cli import build_parser

    p = build_parser()
    args = p.parse_args(["flash", "--port", "/dev/ttyACM0", "--board", "nano"])
    assert args.board == "nano" and callable(args.func)
    args = p.parse_args(["servo", "--virtual", "move", "90", "500"])
    assert (args.angle, args.ms) == (90.0, 500)
    assert np.isfinite(args.angle)


# --------------------------------------------------------------------------- faults

class GarbageDevice(FakeDevice):
    """Answers PING normally but first spits noise, malformed tags and broken reports."""

    NOISE = [b"\x00\xff\xfe garbage \x80\n", b"@\n", b"@abc OK PONG 1\n", b"@-3 OK\n",
             b"@99999999999999999999 OK PONG 1\n", b"START MOVE notanumber\n",
             b"DONE\n", b"STOPPED MOVE 123456789012345678901234567890 x\n",
             b"@\xd9\xa1 OK\n", b"X" * 5000, b"\n", b"START MOVE -5\n", b"\r\r\n"]

    def __init__(self, reply_for_status=None, **kw):
        super().__init__(**kw)
        self.reply_for_status = reply_for_status

    def write(self, data):
        with self.cv:
            for chunk in self.NOISE:
                self.out += chunk
        line = data.decode().strip()
        tag, cmd = line.split(" ", 1)
        if cmd in ("STATUS", "GET LIMITS", "GET PROFILE") and self.reply_for_status is not None:
            self.commands.append(line)
            self.emit(f"{tag} {self.reply_for_status}")
            return len(data)
        return super().write(data)


def test_garbage_from_the_device_never_crashes_the_client():
    dev = GarbageDevice()
    with client_for(dev, timeout=0.5) as c:
        for _ in range(5):
            c.ping()
        assert c._reader is not None and c._reader.is_alive()
        assert all(ev.kind != "START" or ev.device_us >= 0 for ev in c.drain_events())


@pytest.mark.parametrize("reply", ["OK", "OK STATUS", "OK STATUS x y IDLE IDLE",
                                   "OK STATUS nan 90 IDLE IDLE", "OK LIMITS 1 2 3",
                                   "OK PROFILE 90 100", "OK PROFILE 90 100 abc", "OK HELLO"])
def test_malformed_replies_are_protocol_errors(reply):
    dev = GarbageDevice(reply_for_status=reply)
    with client_for(dev, timeout=0.5) as c:
        for call in (c.status, c.get_limits, c.get_profile):
            with pytest.raises(ServoProtocolError, match="malformed"):
                call()
        c.ping()                                    # still talking


class UntaggedErrDevice(FakeDevice):
    """A line garbled on the wire: the firmware answers ERR without the tag."""

    def write(self, data):
        line = data.decode().strip()
        self.commands.append(line)
        if len(self.commands) > 2:                     # after the handshake (PING, HELLO)
            self.emit("ERR BAD_TAG tag unreadable: non-printable byte; line ignored")
            return len(data)
        self.commands.pop()
        return super().write(data)


def test_untagged_error_answers_the_waiting_command_at_once():
    from rig.servo import ServoCommandError

    dev = UntaggedErrDevice()
    with client_for(dev, timeout=2.0, retries=2) as c:
        n0 = len(dev.commands)
        t0 = time.monotonic()
        with pytest.raises(ServoCommandError) as exc:
            c.ping()
        assert time.monotonic() - t0 < 1.0             # no timeout waited
        assert exc.value.untagged and exc.value.code == "BAD_TAG"
        assert "garbled" in str(exc.value)
        assert len(dev.commands) - n0 == 3             # retried: an ERR line had no effect
        with pytest.raises(ServoCommandError):
            c.move(10, 100)                            # motions are never repeated
        assert sum("MOVE" in x for x in dev.commands) == 1


def test_unsolicited_reports_are_bounded(monkeypatch):
    from rig import servo as servo_mod

    dev = FakeDevice()
    with client_for(dev) as c:
        c._events = servo_mod.queue.Queue(maxsize=50)
        for k in range(500):
            dev.emit(f"START MOVE {k}")
        c.ping()
        time.sleep(0.1)
        evs = c.drain_events()
        assert len(evs) == 50 and evs[-1].device_us == 499      # the newest are kept


@pytest.mark.parametrize("call, match", [
    (lambda c: c.move(float("nan"), 100), "move angle"),
    (lambda c: c.move(float("inf"), 100), "move angle"),
    (lambda c: c.move(1e30, 100), "move angle"),
    (lambda c: c.move(-1, 100), "move angle"),
    (lambda c: c.move(90.0001, 100), "3 decimals"),
    (lambda c: c.move(90, 0), "move duration"),
    (lambda c: c.move(90, -5), "move duration"),
    (lambda c: c.move(90, 1e30), "move duration"),
    (lambda c: c.move(90, float("nan")), "move duration"),
    (lambda c: c.move(90, 10.5), "whole number"),
    (lambda c: c.move("ninety", 100), "expected a number"),
    (lambda c: c.turn(181, 100), "turn angle"),
    (lambda c: c.home(70000), "home duration"),
])
def test_client_checks_ranges_before_sending(call, match):
    from rig.servo import ServoInputError

    dev = FakeDevice()
    with client_for(dev) as c:
        n = len(dev.commands)
        with pytest.raises(ServoInputError, match=match):
            call(c)
        assert len(dev.commands) == n                # nothing was sent

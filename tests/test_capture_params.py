"""The capture node's parameters at run time (issue 17): on the closed-loop virtual rig, with the
node on DDS (a private domain), the camera's biases are dynamic parameters ``biases.<name>`` that
a parameter-service client changes while the camera streams (the EVK4 twin sees the register
write); out-of-range values and the read-only options are refused with the reason and change
nothing; each applied change is logged on /rosout with the time it took effect."""

import os
import re
import subprocess
import threading
import time

import pytest

from conftest import ros_domain
import yaml

from rig.capture import CaptureOptions




def _domain() -> int:
    return ros_domain()


def _until(what, timeout_s: float, poll_s: float = 0.02):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        got = what()
        if got:
            return got
        time.sleep(poll_s)
    return what()


def _time_base_on(writes, upto: int) -> bool:
    """Whether the twin's time base ran when write ``upto`` arrived (its last TIME_BASE_CTRL write
    before it enabled the time base)."""
    from rig.camera import evk4_registers as R

    for address, value in reversed(writes[:upto]):
        if address == R.TIME_BASE_CTRL:
            return bool(value & R.TIME_BASE_ENABLE)
    return False


def test_biases_change_live_and_the_options_stay_read_only(virtual_rig, tmp_path):
    from evdnerf_ros.ros import rostypes
    from evdnerf_ros.ros.param_services import DOUBLE, INTEGER, ParameterClient, from_parameter_value
    from evdnerf_ros.ros.qos import LOOPBACK_XML, PROFILES
    from evdnerf_ros.ros.transport import DdsContext, DdsSubscription
    from rig.camera import evk4_registers as R
    from rig.capture_cli import RigChoice, spawn_virtual_capture

    vr, out = virtual_rig, tmp_path / "S"
    domain = _domain()
    env = {k: v for k, v in os.environ.items()
           if k not in ("RMW_IMPLEMENTATION", "CYCLONEDDS_URI", "ROS_AUTOMATIC_DISCOVERY_RANGE")}
    env.update(ROS_DOMAIN_ID=str(domain), ROS_LOCALHOST_ONLY="1")
    bias_file = tmp_path / "start.bias"
    bias_file.write_text("% applied by the session before its first view\n7 % bias_fo\n")
    rig = RigChoice(output=str(out), live=True)
    opts = CaptureOptions(views=3, turn_ms=300, home_ms=300, pre_roll_s=0.1, settle_s=0.1, bias_file=str(bias_file))
    proc = spawn_virtual_capture(vr, rig, opts, tmp_path, env=env, stdout=subprocess.PIPE,
                                 stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    ctx = DdsContext(domain, config=LOOPBACK_XML)
    try:
        rosout = DdsSubscription(ctx, "/rosout", "rcl_interfaces/msg/Log", PROFILES["parameters"])
        events = DdsSubscription(ctx, "/parameter_events", "rcl_interfaces/msg/ParameterEvent",
                                 PROFILES["parameters"])
        client = ParameterClient(ctx, "/capture")
        assert client.wait_for_service(30.0), "".join(lines)

        # one integer parameter per bias of the camera, declared once it is open, with the
        # driver's range; the values are what the twin holds (offsets from its factory values)
        def bias_names():
            return [n for n in client.list(prefixes=["biases"]) if n.startswith("biases.")]

        names = _until(bias_names, 30.0, 0.1)
        assert names == [f"biases.{n}" for n in R.BIASES], "".join(lines)
        # the session's bias file goes through the parameters too (they follow the camera's read-back)
        assert _until(lambda: vr.twin.bias_offsets()["bias_fo"] == 7, 10.0), "".join(lines)
        held = vr.twin.bias_offsets()
        want = [held[n.split(".", 1)[1]] for n in names]
        assert _until(lambda: client.get(*names) == want, 5.0, 0.05), (client.get(*names), want)
        (desc,) = client.describe("biases.bias_diff_on")
        assert (desc.type, desc.read_only) == (INTEGER, False)
        # OpenEB's allowed range narrowed to what the 8-bit register holds from the factory value
        lo, hi = R.BIAS_RANGES["bias_diff_on"][:2]
        f = vr.twin.factory["bias_diff_on"]
        want_range = (max(lo, -f), min(hi, 255 - f))
        assert (desc.integer_range[0].from_value, desc.integer_range[0].to_value) == want_range

        # a set while the camera streams reaches the twin's bias register, and the node logs (on
        # /rosout) when it took effect, in sensor time; sets go 0.15 s into a view (which records
        # for 1.1 s), another value is tried only when a slow machine still missed the stream
        address = R.BIASES["bias_diff_on"].address
        factory = vr.twin.factory["bias_diff_on"]
        said: list[str] = []

        def applied(v):
            said.extend(rostypes.deserialize(d, "rcl_interfaces/msg/Log").msg for d, _ in rosout.take_raw(1000))
            return [m for m in said if f"biases {{'bias_diff_on': {v}}} applied (parameter service)" in m]

        for value in (20, 21, 22):
            assert _until(lambda: vr.twin.streaming, 20.0, 0.005), "".join(lines)
            time.sleep(0.15)
            mark = len(vr.twin.register_writes())
            assert client.set(**{"biases.bias_diff_on": value}) == [(True, "")]
            writes = vr.twin.register_writes()
            mine = [i for i in range(mark, len(writes)) if writes[i][0] == address]
            assert [writes[i][1] for i in mine] == [R.bias_register_value(factory + value)], writes[mark:]
            line = _until(lambda: applied(value), 5.0, 0.05)
            assert line and "wall clock" in line[0], said
            if _time_base_on(writes, mine[0]) and re.search(r"sensor time -?\d+ ns", line[0]):
                break
        else:
            pytest.fail(f"no bias set landed while the camera streamed: {said}")
        assert vr.twin.bias_offsets()["bias_diff_on"] == value
        assert client.get("biases.bias_diff_on") == [value]

        # refused with the reason, nothing written: out of range, the wrong type, half of an
        # atomic set, the read-only options (the bias file's path among them)
        mark = len(vr.twin.register_writes())
        before = vr.twin.bias_offsets()
        [(ok, why)] = client.set(**{"biases.bias_diff_on": want_range[1] + 1})      # one past the register
        assert not ok and "outside its range" in why and str(want_range[1]) in why, why
        ok, why = client.set_typed("biases.bias_fo", 1.5, DOUBLE)
        assert not ok and "is of type {integer}" in why, why
        [(ok, why)] = client.set(atomically=True, **{"biases.bias_fo": 5, "biases.bias_diff_off": 10_000})
        assert not ok and "outside its range" in why, why
        for name, v in (("views", 7), ("bias_file", "/tmp/other.bias"), ("c_pos", 0.3)):
            [(ok, why)] = client.set(**{name: v})
            assert not ok and f"parameter {name!r} is read-only while the node runs" in why, why
        assert vr.twin.register_writes(mark) == [] and vr.twin.bias_offsets() == before
        assert client.get("biases.bias_diff_on", "biases.bias_fo", "views") == [value, before["bias_fo"], 3]

        # the applied value on /parameter_events, as ros2 param set shows it
        changed = _until(lambda: [(p.name, from_parameter_value(p.value)[1]) for d, _ in events.take_raw(1000)
                                  for p in rostypes.deserialize(d, "rcl_interfaces/msg/ParameterEvent")
                                  .changed_parameters], 5.0, 0.05)
        assert ("biases.bias_diff_on", value) in changed, changed

        code = proc.wait(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        ctx.close()
    reader.join(5)
    text = "".join(lines)
    assert code == 0, text
    assert "Traceback" not in text and "biases {'bias_fo': 7} applied (bias file)" in text, text
    session = yaml.safe_load((out / "session.yaml").read_text())
    assert len(session["views"]) == 3 and all(v["complete"] for v in session["views"]), text
    assert session["camera"]["biases"]["bias_fo"] == 7           # read once, after the bias file
    # per view: the biases in force, every live change once (with its sensor time, values and
    # the thresholds after it), and the thresholds the driver's model gives (the twin's own model:
    # tests/test_capture_stream.py; the camera is back at its factory biases once closed)
    from rig.camera.evk4 import thresholds_from_biases

    views = session["views"]
    moves = [m for v in views for m in v["bias_changes"]]
    assert [m["values"] for m in moves] == [{"bias_diff_on": v} for v in range(20, value + 1)], moves
    assert all(m["source"] == "parameter service" and m["when"] in ("before", "recording") for m in moves)
    # sensor time on the stream's arrival clock (the one the views are cut by): a change made while
    # a view recorded lies after that clock's zero; one made before the first view may precede it
    # when the twin renders slower than real time (its data arrive late, the clock's zero with them)
    assert isinstance(moves[-1]["sensor_ns"], int), moves
    assert moves[-1]["when"] == "before" or moves[-1]["sensor_ns"] > 0, moves
    off = session["camera"]["biases"]["bias_diff_off"]
    assert moves[-1]["thresholds"] == pytest.approx(dict(zip(("c_pos", "c_neg"), thresholds_from_biases(value, off))))
    assert views[0]["biases"]["bias_fo"] == 7 and views[-1]["biases"]["bias_diff_on"] == value
    last = views[-1]["thresholds"]
    assert views[-1]["thresholds_source"] == "bias model"
    assert (last["c_pos"], last["c_neg"]) == pytest.approx(thresholds_from_biases(value, off)) != (0.2, 0.2)
    # a change counts from its time on: a view has the biases of the changes before it
    running = dict(session["camera"]["biases"])
    for v in views:
        running.update({n: x for m in v["bias_changes"] if m["when"] == "before" for n, x in m["values"].items()})
        assert v["biases"] == running, (v["biases"], running)
        assert (v["thresholds"]["c_pos"], v["thresholds"]["c_neg"]) == pytest.approx(
            thresholds_from_biases(running["bias_diff_on"], running["bias_diff_off"]))
        running.update({n: x for m in v["bias_changes"] for n, x in m["values"].items()})

def test_capture_options_are_read_only_parameters():
    """Without DDS too: every option is declared (lists without a numeric range) and a run-time
    set is refused with the reason; nothing changes."""
    from rig.capture_cli import CaptureNode, RigChoice, _node_values

    node = CaptureNode([], overrides=_node_values(RigChoice(output="S"), CaptureOptions(views=3)), dds=False)
    assert node.params["views"] == 3 and node.params["look_at"] == [0.0, 0.0, -0.3]
    reasons = node.params.set_runtime([("views", 5), ("look_at", [1.0, 2.0, 3.0]), ("bias_file", "x.bias")], "t")
    assert all(r and "read-only while the node runs" in r for r in reasons), reasons
    assert node.params["views"] == 3 and node.params["bias_file"] == ""


@pytest.mark.parametrize("model, bias, bad", [("EVK4", "bias_diff_on", 201), ("DVXplorer", "current_on", 9),
                                              ("DVXplorer", "current_range_log", 2),
                                              ("DAVIS346", "diffbn_coarse", 8), ("DAVIS346", "apscas_voltage", 64)])
def test_bias_checks_are_the_drivers_own(model, bias, bad):
    """What the capture node checks before a set (bias_limits, check_bias_values) is what the
    driver's set_biases refuses, same text, and its top value passes (no camera needed: the
    drivers check before they write)."""
    from rig.camera import driver_class
    from rig.camera.errors import CameraError
    from rig.capture_cli import bias_limits, check_bias_values

    device = driver_class(model)()
    limits = bias_limits(device)
    assert limits[bias][1] == bad - 1
    device._is_open = True                      # set_biases refuses an unopened camera before it checks
    with pytest.raises(CameraError) as driver:
        device.set_biases({bias: bad})
    with pytest.raises(CameraError) as ours:
        check_bias_values(device, {bias: bad}, limits)
    assert str(ours.value) == str(driver.value)
    assert check_bias_values(device, {bias: bad - 1}, limits) == {bias: bad - 1}
    with pytest.raises(CameraError, match="unknown bias"):
        check_bias_values(device, {"bias_nope": 0}, limits)

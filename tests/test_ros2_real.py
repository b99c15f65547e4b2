"""The package under a real ROS 2 Jazzy (``../shared/ros2``), as a ROS user runs it: built with
docs/ros2.md's recipe into an overlay (normal and ``--symlink-install``), then ``ros2 launch`` /
``ros2 node`` / ``topic`` / ``param`` / ``bag`` and rclpy against our nodes, under the standard
Jazzy environment (``setup.bash`` sets ``ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET``) with
``ROS_LOCALHOST_ONLY=1``. Skipped where the real ROS 2 or colcon is absent (``real_ros2.missing``)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import textwrap
import time
from pathlib import Path

import pytest

import real_ros2
from conftest import ros_domain

pytestmark = pytest.mark.skipif(real_ros2.missing() is not None, reason=str(real_ros2.missing()))

EVENT_PACKET = "event_camera_msgs/msg/EventPacket"


#: The ROS_DOMAIN_IDs the tests used: `ros2 param` / `service` start a ros2 daemon in each.
_DOMAINS: set[str] = set()


@pytest.fixture(scope="module")
def installs(tmp_path_factory):
    """Both colcon installs of the package: {'normal': Overlay, 'symlink': Overlay}; the ros2
    daemons the tests started are stopped at the end."""
    root = tmp_path_factory.mktemp("ros2_ws")
    built = {name: real_ros2.overlay(root / name, symlink=name == "symlink") for name in ("normal", "symlink")}
    yield built
    for domain in sorted(_DOMAINS):
        built["normal"].run("ros2 daemon stop", env={"ROS_LOCALHOST_ONLY": "1", "ROS_DOMAIN_ID": domain})


def _env() -> dict:
    domain = str(ros_domain())
    _DOMAINS.add(domain)
    return {"ROS_LOCALHOST_ONLY": "1", "ROS_DOMAIN_ID": domain}


def _wait_for(ws, env, cmd: str, wanted: str, timeout=60.0) -> str:
    """Run a ros2 CLI command until its output contains ``wanted``; its last output."""
    deadline = time.monotonic() + timeout
    out = ""
    while time.monotonic() < deadline:
        r = ws.run(cmd, env=env, timeout=60)
        out = r.stdout + r.stderr
        if wanted in out:
            return out
        time.sleep(0.5)
    raise AssertionError(f"`{cmd}` never showed {wanted!r}; last output:\n{out}")


def _start(ws, args, env, log: Path) -> subprocess.Popen:
    """A long-running command whose output goes to ``log`` (a pipe nobody reads would fill and
    block the node's logging, as a terminal never does)."""
    with open(log, "w") as out:
        proc = ws.popen(args, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    proc.log = log
    return proc


def _finish(proc: subprocess.Popen, timeout) -> tuple[int, str]:
    try:
        proc.wait(timeout=timeout)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return proc.returncode, proc.log.read_text()


def _stop(proc: subprocess.Popen, timeout=30) -> tuple[int, str]:
    """Ctrl-C, as a user's terminal sends it (to the whole process group: `ros2 run` and the
    node, `ros2 launch` and its children): the exit status and output."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGINT)
    return _finish(proc, timeout)


def _rclpy(ws, env, code: str, timeout=90) -> subprocess.CompletedProcess:
    return ws.run([ws.python, "-c", textwrap.dedent(code)], env=env, timeout=timeout)


@pytest.mark.parametrize("kind", ["normal", "symlink"])
def test_colcon_install_holds_the_executables_and_the_share_data(installs, kind):
    ws = installs[kind]
    r = ws.run("ros2 pkg executables rig")
    assert r.returncode == 0, r.stderr
    assert set(r.stdout.split()) >= {"rig", "capture", "event_publisher", "evdnerf"}
    share = Path(ws.run("ros2 pkg prefix --share rig").stdout.strip())
    for rel in ("launch/capture.launch.py", "launch/publish.launch.py", "config/capture.yaml",
                "config/event_publisher.yaml", "firmware", "package.xml"):
        assert (share / rel).exists(), rel


@pytest.mark.parametrize("kind", ["normal", "symlink"])
def test_publish_launch_is_a_member_of_the_graph(installs, kind, tmp_path):
    """`ros2 launch rig publish.launch.py scene:=fork` under ROS_LOCALHOST_ONLY=1: seen by the
    ROS 2 CLI, its events received by an rclpy subscriber, stopped by Ctrl-C with exit 0."""
    ws, env = installs[kind], _env()
    proc = _start(ws, ["ros2", "launch", "rig", "publish.launch.py", "scene:=fork", "realtime_factor:=0.5"],
                  env, tmp_path / "launch.log")
    try:
        _wait_for(ws, env, "ros2 node list --no-daemon", "/event_publisher")
        topics = ws.run("ros2 topic list -t --no-daemon", env=env).stdout
        assert f"/event_publisher/events [{EVENT_PACKET}]" in topics, topics
        assert "/event_publisher/camera_info [sensor_msgs/msg/CameraInfo]" in topics, topics
        r = ws.run("ros2 param get /event_publisher scene", env=env)
        assert r.stdout.strip() == "String value is: fork", r.stdout + r.stderr
        r = ws.run("ros2 param get /event_publisher use_sim_time", env=env)
        assert r.stdout.strip() == "Boolean value is: False", r.stdout + r.stderr
        r = ws.run("ros2 param set /event_publisher c_pos 0.25", env=env)
        assert "Set parameter successful" in r.stdout, r.stdout + r.stderr
        r = ws.run("ros2 param set /event_publisher run_dir /tmp", env=env)
        assert "read-only" in (r.stdout + r.stderr).lower(), r.stdout + r.stderr
        services = ws.run("ros2 service list --no-daemon", env=env).stdout
        assert "/event_publisher/get_type_description" in services, services
        # an rclpy subscriber receives EventPackets in the sensor's encoding, in order
        got = _rclpy(ws, env, f"""
            import json, rclpy
            from event_camera_msgs.msg import EventPacket
            rclpy.init(); node = rclpy.create_node("listener"); msgs = []
            node.create_subscription(EventPacket, "/event_publisher/events", msgs.append, 10)
            end = node.get_clock().now().nanoseconds + 40 * 10**9
            while len(msgs) < 5 and node.get_clock().now().nanoseconds < end:
                rclpy.spin_once(node, timeout_sec=0.2)
            stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in msgs]
            print(json.dumps(dict(n=len(msgs), enc=sorted({{m.encoding for m in msgs}}),
                                  size=[msgs[0].width, msgs[0].height] if msgs else None, stamps=stamps)))
            """)
        assert got.returncode == 0, got.stderr
        res = json.loads(got.stdout.strip().splitlines()[-1])
        assert res["n"] >= 5 and res["enc"] == ["evt3"] and res["size"][0] > 0, res
        assert res["stamps"] == sorted(res["stamps"]), res
    finally:
        rc, out = _stop(proc)
    assert rc == 0, out[-3000:]
    assert "process has finished cleanly" in out, out[-3000:]


def test_capture_launch_on_the_virtual_rig_makes_a_session_that_trains(installs, tmp_path, rig_lock):
    """`ros2 launch rig capture.launch.py ... virtual:=true views:=2`: its launch arguments are its
    parameters (`ros2 param get`), its bags are read by `ros2 bag info`, and sync and convert turn
    the session into a training set."""
    ws, env = installs["normal"], _env()
    session = tmp_path / "session"
    proc = _start(ws, ["ros2", "launch", "rig", "capture.launch.py", f"output:={session}", "virtual:=true", "views:=2"],
                  env, tmp_path / "launch.log")
    try:
        _wait_for(ws, env, "ros2 param get /capture virtual", "Boolean value is: True", timeout=40)
        r = ws.run("ros2 param get /capture views", env=env)
        assert r.stdout.strip() == "Integer value is: 2", r.stdout + r.stderr
    finally:
        rc, out = _finish(proc, 240)
    assert rc == 0 and "process has finished cleanly" in out, out[-3000:]
    for view in ("view_00", "view_01"):
        info = ws.run(["ros2", "bag", "info", str(session / view)]).stdout
        assert f"/event_camera/events | Type: {EVENT_PACKET}" in info, info
        assert "/rig/servo/trigger | Type: sensor_msgs/msg/TimeReference" in info, info
    for cmd in (["sync", str(session)], ["convert", str(session), "-o", str(tmp_path / "train.h5")]):
        r = ws.run(["ros2", "run", "rig", "evdnerf", *cmd], timeout=300)
        assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    from evdnerf_ros.io.trainingset import TrainingSet

    with TrainingSet(tmp_path / "train.h5") as ts:
        assert len(ts.views) == 2 and ts.width > 0


def test_a_launch_argument_of_the_wrong_type_is_a_one_line_error(installs, tmp_path):
    ws, env = installs["normal"], _env()
    r = ws.run(["ros2", "launch", "rig", "capture.launch.py", f"output:={tmp_path / 's'}", "views:=two"],
               env=env, timeout=60)
    out = r.stdout + r.stderr
    assert "views" in out and "Traceback" not in out, out[-3000:]
    assert "process has died" in out or r.returncode != 0, out[-3000:]
    assert not (tmp_path / "s").exists()


def test_rclpy_follows_our_clock_and_our_bag_replays_with_ros2_bag(installs, tmp_path):
    """An rclpy node with use_sim_time follows the publisher's /clock; `ros2 bag record` of the
    publisher reads back with our tools, and `ros2 bag play` of our own bag reaches `evdnerf echo`."""
    ws, env = installs["normal"], _env()
    ours = tmp_path / "ours_bag"
    proc = _start(ws, ["ros2", "run", "rig", "event_publisher", "--ros-args", "-p", "scene:=fork",
                       "-p", "realtime_factor:=0.5", "-p", "duration:=6.0", "-p", "camera.width:=64",
                       "-p", "camera.height:=48", "-p", f"bag:={ours}"],
                  env, tmp_path / "publisher.log")
    recorded = tmp_path / "recorded"
    rec = _start(ws, ["ros2", "bag", "record", "-o", str(recorded), "/event_publisher/events"],
                 env, tmp_path / "record.log")
    try:
        got = _rclpy(ws, env, """
            import json, rclpy
            from rclpy.parameter import Parameter
            rclpy.init()
            node = rclpy.create_node("sim_clock", parameter_overrides=[Parameter("use_sim_time", value=True)])
            seen = []
            end = rclpy.clock.Clock().now().nanoseconds + 40 * 10**9
            while len(seen) < 20 and rclpy.clock.Clock().now().nanoseconds < end:
                rclpy.spin_once(node, timeout_sec=0.05)
                t = node.get_clock().now().nanoseconds
                if t and (not seen or t != seen[-1]):
                    seen.append(t)
            print(json.dumps(seen))
            """)
        assert got.returncode == 0, got.stderr
        seen = json.loads(got.stdout.strip().splitlines()[-1])
        # the trajectory's time, not the wall clock's: a few seconds from the scene's start, rising
        assert len(seen) >= 5 and seen == sorted(seen) and seen[-1] < 60 * 10**9, seen
        rc, out = _finish(proc, 300)
        assert rc == 0, out[-3000:]
    finally:
        for p in (proc, rec):
            _stop(p)
    info = ws.run(["ros2", "bag", "info", str(ours)]).stdout
    assert f"/event_publisher/events | Type: {EVENT_PACKET}" in info, info
    r = ws.run(["ros2", "run", "rig", "evdnerf", "info", str(recorded), "--json"])
    assert r.returncode == 0, r.stdout + r.stderr
    assert json.loads(r.stdout)["events"]["count"] > 0, r.stdout

    echo = ws.popen(["ros2", "run", "rig", "evdnerf", "echo", "/event_publisher/events", "--count", "3",
                     "--duration", "60", "--json"], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    time.sleep(3)
    play = ws.run(["ros2", "bag", "play", str(ours)], env=env, timeout=120)
    assert play.returncode == 0, play.stderr[-2000:]
    out, err = echo.communicate(timeout=60)
    assert echo.returncode == 0, out[-2000:] + err[-2000:]
    assert json.loads(out)["messages"] >= 3, out


def test_a_bad_params_file_names_the_file_and_the_parameter(installs, tmp_path):
    ws, env = installs["normal"], _env()
    bad = tmp_path / "bad.yaml"
    bad.write_text("event_publisher:\n  ros__parameters:\n    realtime_factor: fast\n")
    r = ws.run(["ros2", "run", "rig", "event_publisher", "--ros-args", "--params-file", str(bad)], env=env, timeout=60)
    out = r.stdout + r.stderr
    assert r.returncode != 0 and "Traceback" not in out, out
    assert str(bad) in out and "realtime_factor" in out, out


def test_a_storm_of_parameter_sets_leaves_the_node_publishing_and_its_bag_whole(installs, tmp_path):
    """5,000 set_parameters requests from rclpy in one burst (valid, out of range, wrong type,
    read-only, unknown) while the publisher records: the services' QoS (keep last 10) drops what
    the node cannot take in time, as it does for any ROS 2 server; the node keeps serving
    (`ros2 param set` / `get` right after), keeps publishing and closes its bag on Ctrl-C."""
    ws, env = installs["normal"], _env()
    bag = tmp_path / "bag"
    proc = _start(ws, ["ros2", "run", "rig", "event_publisher", "--ros-args", "-p", "scene:=fork",
                       "-p", "realtime_factor:=0.5", "-p", "duration:=60.0", "-p", f"bag:={bag}"],
                  env, tmp_path / "publisher.log")
    try:
        got = _rclpy(ws, env, """
            import json, rclpy
            from rclpy.parameter import Parameter
            from rcl_interfaces.srv import SetParameters
            rclpy.init(); node = rclpy.create_node("storm")
            cli = node.create_client(SetParameters, "/event_publisher/set_parameters")
            assert cli.wait_for_service(timeout_sec=30)
            values = [("c_pos", 0.3), ("c_pos", -1.0), ("c_pos", "x"), ("run_dir", "/tmp"), ("no_such", 1)]
            futures = [cli.call_async(SetParameters.Request(parameters=[Parameter(*values[i % 5][:1],
                       value=values[i % 5][1]).to_parameter_msg()])) for i in range(5000)]
            end = node.get_clock().now().nanoseconds + 10 * 10**9
            while node.get_clock().now().nanoseconds < end:
                rclpy.spin_once(node, timeout_sec=0.05)
            done = [f.result().results[0] for f in futures if f.done()]
            ok = [r.successful for r, f in zip(done, [f for f in futures if f.done()])]
            print(json.dumps(dict(done=len(done), ok=sum(ok))))
            """, timeout=120)
        assert got.returncode == 0, got.stderr
        res = json.loads(got.stdout.strip().splitlines()[-1])
        assert res["done"] >= 1, res
        r = ws.run("ros2 param set /event_publisher c_pos 0.21", env=env)
        assert "Set parameter successful" in r.stdout, r.stdout + r.stderr
        r = ws.run("ros2 param get /event_publisher c_pos", env=env)
        assert r.stdout.strip() == "Double value is: 0.21", r.stdout + r.stderr
        assert proc.poll() is None, "the node stopped during the storm"
    finally:
        rc, out = _stop(proc, timeout=60)
    assert rc == 0, out[-3000:]
    info = ws.run(["ros2", "bag", "info", str(bag)]).stdout
    assert f"/event_publisher/events | Type: {EVENT_PACKET}" in info, info

"""The event publisher node without DDS: trajectory inputs and their bad-input errors,
extrinsics, checkpoints from another version, the event stream against the offline
generator, leave-out switches, stability cases, and `evdnerf publish`."""

import math

import numpy as np
import pytest
import yaml

from evdnerf_ros.cli import main
from evdnerf_ros.errors import EvdnerfError, InputError
from evdnerf_ros.geometry.rotations import matrix_to_quat, quat_from_ros, quat_to_matrix, quat_to_ros
from evdnerf_ros.io import messages
from evdnerf_ros.io.poses import extrinsics, load_poses
from evdnerf_ros.io.rosbag2 import BagWriter, open_bag, read_events
from evdnerf_ros.nodes.event_publisher import EventPublisher, run_node
from evdnerf_ros.geometry.camera import PinholeCamera, look_at
from evdnerf_ros.sim.generator import EventGenerator
from evdnerf_ros.geometry.pose_track import PoseTrack
from evdnerf_ros.sim.render import SceneRenderer
from evdnerf_ros.sim.scene import load_scene


def quat_to_matrix_ros(q_xyzw):
    return quat_to_matrix(quat_from_ros(q_xyzw))


def matrix_to_quat_ros(R):
    return quat_to_ros(matrix_to_quat(R))

EVENTS = "/event_publisher/events"
SMALL = {"camera.width": 24, "camera.height": 24, "realtime_factor": 0.0, "adaptive": False,
         "render_rate_hz": 1000.0}


def publish(tmp_path, name="b", **params):
    """Run the node bag-only; returns (report, bag path)."""
    bag = tmp_path / name
    rep = run_node((), overrides={**SMALL, "bag": str(bag), **params}, dds=False)
    return rep, bag


def offline_events(w, h, t_end_ns, offset_ns, rate_hz=1000, **gen):
    """The reference: frames of the static default view at a fixed rate through one EventGenerator."""
    scene = load_scene("fork", check_cameras=False)
    cam = PinholeCamera.from_fov(w, h, scene.camera.fov_x_deg)
    render = SceneRenderer(scene, cam, 1)
    T = scene.camera_poses("train")[0]
    n = round(t_end_ns * rate_hz / 1e9)
    times = np.arange(n + 1, dtype=np.int64) * (t_end_ns // n)
    frames = [render(T, int(t) + offset_ns) for t in times]
    return EventGenerator(w, h, **gen).generate(frames, times)


# ----------------------------------------------------------------------------- trajectories

def _circle(n=21, span_ns=1_000_000_000, t0=0):
    t = t0 + np.arange(n, dtype=np.int64) * (span_ns // (n - 1))
    poses = []
    for k in range(n):
        a = 2 * math.pi * k / (n - 1) * 0.25
        poses.append({"t_ns": int(t[k]), "position": [math.cos(a), math.sin(a), 0.5],
                      "orientation": [0.0, 0.0, math.sin(a / 2), math.cos(a / 2)]})
    return t, poses


def test_yaml_csv_and_bag_trajectories_agree(tmp_path):
    t, poses = _circle()
    y = tmp_path / "traj.yaml"
    y.write_text(yaml.safe_dump({"frame_id": "world", "poses": poses}))
    c = tmp_path / "traj.csv"
    c.write_text("t,x,y,z,qx,qy,qz,qw\n" + "".join(
        f"{p['t_ns'] / 1e9!r},{','.join(map(repr, p['position'] + p['orientation']))}\n" for p in poses))
    T_ref = load_poses(y)[1]
    for kind in ("pose", "odom", "tf"):
        b = tmp_path / f"{kind}_bag"
        with BagWriter(b) as w:
            for p, T in zip(poses, T_ref):
                stamp = p["t_ns"] + 5
                if kind == "pose":
                    w.write("/robot/pose", "geometry_msgs/msg/PoseStamped", messages.pose_stamped(T, stamp), stamp)
                    continue
                types = w.typestore.types
                ps = messages.pose_stamped(T, stamp)
                if kind == "odom":
                    cov = types["geometry_msgs/msg/PoseWithCovariance"](pose=ps.pose, covariance=np.zeros(36))
                    tw = types["geometry_msgs/msg/TwistWithCovariance"](
                        twist=types["geometry_msgs/msg/Twist"](linear=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                                                               angular=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
                        covariance=np.zeros(36))
                    w.write("/odom", "nav_msgs/msg/Odometry", types["nav_msgs/msg/Odometry"](
                        header=ps.header, child_frame_id="base_link", pose=cov, twist=tw), stamp)
                else:
                    o, q = ps.pose.position, ps.pose.orientation
                    tf = types["geometry_msgs/msg/TransformStamped"](
                        header=ps.header, child_frame_id="base_link", transform=types["geometry_msgs/msg/Transform"](
                            translation=types["geometry_msgs/msg/Vector3"](x=o.x, y=o.y, z=o.z), rotation=q))
                    other = types["geometry_msgs/msg/TransformStamped"](
                        header=ps.header, child_frame_id="camera_mount", transform=tf.transform)
                    w.write("/tf", "tf2_msgs/msg/TFMessage", types["tf2_msgs/msg/TFMessage"](transforms=[other, tf]),
                            stamp)
        tb, Tb = load_poses(b)
        np.testing.assert_array_equal(tb, t + 5)
        np.testing.assert_allclose(Tb, T_ref, atol=1e-12)
    tc, Tc = load_poses(c)
    np.testing.assert_array_equal(tc, t)
    np.testing.assert_allclose(Tc, T_ref, atol=1e-12)


def test_pose_track_slerps_and_interpolates_linearly():
    T0, T1 = np.eye(4), np.eye(4)
    T1[:3, :3] = quat_to_matrix_ros([0, 0, math.sin(math.pi / 4), math.cos(math.pi / 4)])  # 90 deg yaw
    T1[:3, 3] = [2.0, 0.0, 0.0]
    track = PoseTrack([10, 110], [T0, T1])
    mid = track(60)
    np.testing.assert_allclose(mid[:3, 3], [1.0, 0.0, 0.0])
    np.testing.assert_allclose(mid[:3, :3], quat_to_matrix_ros(
        [0, 0, math.sin(math.pi / 8), math.cos(math.pi / 8)]), atol=1e-12)
    np.testing.assert_allclose(track(110), T1, atol=1e-12)
    with pytest.raises(InputError, match="outside the trajectory"):
        track(111)


def test_pose_track_gives_many_poses_at_once_as_one_by_one():
    """``poses(times)`` (the per-pixel sampler's batch) equals slerp of each segment's pair, time by time."""
    from evdnerf_ros.geometry.rotations import quat_to_matrix, slerp

    rng = np.random.default_rng(4)
    t = np.array([0, 40, 100, 260, 300], np.int64)
    T = np.stack([np.eye(4)] * 5)
    for k in range(5):
        q = rng.normal(size=4)
        T[k, :3, :3] = quat_to_matrix(q / np.linalg.norm(q))
        T[k, :3, 3] = rng.normal(size=3)
    track = PoseTrack(t, T)
    times = np.array([0, 5, 40, 41, 99, 100, 180, 299, 300], np.int64)
    many = track.poses(times)
    assert many.shape == (9, 4, 4)
    for k, tt in enumerate(times):
        i = min(int(np.searchsorted(t, tt, "right")) - 1, 3)
        u = (tt - t[i]) / (t[i + 1] - t[i])
        want = np.eye(4)
        want[:3, :3] = quat_to_matrix(slerp(track.q[i], track.q[i + 1], u))
        want[:3, 3] = track.p[i] + u * (track.p[i + 1] - track.p[i])
        np.testing.assert_allclose(many[k], want, rtol=0, atol=1e-15)
        np.testing.assert_array_equal(track(int(tt)), many[k])
    np.testing.assert_allclose(many[[2, 5, 8]], T[[1, 2, 4]], atol=1e-12)     # at the poses themselves
    with pytest.raises(InputError, match="time 301 ns is outside"):
        track.poses([0, 301])


@pytest.mark.parametrize("mutate,match", [
    (lambda p: p[3].update(t_ns=p[2]["t_ns"]), "does not come after pose 2"),
    (lambda p: p[5].update(t_ns=p[1]["t_ns"] - 1), "does not come after"),
    (lambda p: p[4].update(position=[0.0, float("nan"), 0.0]), "pose 4 has NaN"),
    (lambda p: p[2].update(orientation=[0.0, 0.0, 0.0, 2.0]), "norm 2"),
    (lambda p: p.__delitem__(slice(1, None)), "at least 2"),
    (lambda p: p[0].pop("position"), "pose 0 needs"),
])
def test_bad_yaml_trajectories_name_file_and_pose(tmp_path, mutate, match):
    _, poses = _circle()
    mutate(poses)
    f = tmp_path / "bad.yaml"
    f.write_text(yaml.safe_dump({"poses": poses}))
    with pytest.raises(InputError, match=match) as err:
        load_poses(f)
    assert str(f) in str(err.value)


def test_bad_csv_and_gaps(tmp_path):
    f = tmp_path / "bad.csv"
    f.write_text("t_ns,x,y,z\n0,1,2,3\n")
    with pytest.raises(InputError, match="need t_ns"):
        load_poses(f)
    f.write_text("t_ns,x,y,z,qx,qy,qz,qw\n0,0,0,0,0,0,0,1\n10,nan,0,0,0,0,0,1\n")
    with pytest.raises(InputError, match="line 3.*NaN"):
        load_poses(f)
    f.write_text("t_ns,x,y,z,qx,qy,qz,qw\n0,0,0,0,0,0,0,1\n2000000000,1,0,0,0,0,0,1\n")
    with pytest.raises(InputError, match="gap of 2.000 s.*max_gap 0.5"):
        EventPublisher((), overrides={**SMALL, "trajectory": str(f)}, dds=False)
    with pytest.raises(InputError, match="no such trajectory"):
        load_poses(tmp_path / "missing.yaml")


def test_extrinsics_must_be_rigid(tmp_path):
    T = extrinsics([0.1, 0, 0], [0, 0, 90])
    np.testing.assert_allclose(T[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    _, poses = _circle()
    f = tmp_path / "t.yaml"
    f.write_text(yaml.safe_dump({"poses": poses}))
    scaled = (np.diag([2.0, 1.0, 1.0, 1.0])).ravel().tolist()
    for bad, match in [({"camera.matrix": scaled}, "camera.matrix.*not a proper rotation"),
                       ({"camera.quat": [0.0, 0.0, 0.0, 3.0]}, "camera.quat.*norm 3"),
                       ({"camera.xyz": [0.0, float("nan"), 0.0]}, "camera.xyz.*finite")]:
        with pytest.raises(InputError, match=match):
            EventPublisher((), overrides={**SMALL, "trajectory": str(f), "bag": str(tmp_path / "never"), **bad},
                           dds=False)
    assert not (tmp_path / "never").exists()


def test_checkpoint_from_another_version_is_refused(tmp_path):
    import torch

    from evdnerf_ros.train.checkpoint import FORMAT, FORMAT_VERSION

    run = tmp_path / "run"
    run.mkdir()
    torch.save({"format": FORMAT, "format_version": FORMAT_VERSION, "software_version": "99.0.0"},
               run / "checkpoint.pt")
    _, poses = _circle()
    f = tmp_path / "t.yaml"
    f.write_text(yaml.safe_dump({"poses": poses}))
    with pytest.raises(InputError, match=r"checkpoint.pt: written by evdnerf_ros 99.0.0.*retrain"):
        run_node((), overrides={**SMALL, "run_dir": str(run), "trajectory": str(f), "bag": str(tmp_path / "b")},
                 dds=False)
    assert not (tmp_path / "b").exists() and sorted(p.name for p in tmp_path.iterdir()) == ["run", "t.yaml"]


# ----------------------------------------------------------------------------- the event stream

@pytest.mark.parametrize("encoding", ["mono", "evt3", "array"])
def test_published_stream_equals_offline_generator(tmp_path, encoding):
    offset = 150_000_000
    rep, bag = publish(tmp_path, encoding=encoding, duration=0.06, scene_time_offset=offset / 1e9, chunk=0.02)
    ref = offline_events(24, 24, 60_000_000, offset)
    assert ref.size > 200
    if encoding == "evt3":
        from evdnerf_ros.events.codecs import quantize_to_us

        ref = quantize_to_us(ref, time_base_ns=0)
    got = read_events(bag, EVENTS).events
    np.testing.assert_array_equal(got, ref)
    assert rep.events == ref.size and not rep.interrupted
    with open_bag(bag) as b:
        infos = list(b.read_messages("/event_publisher/camera_info"))
        assert len(infos) == 1
        info = messages.intrinsics_from_camera_info(infos[0][1])
        cam = PinholeCamera.from_fov(24, 24, load_scene("fork", check_cameras=False).camera.fov_x_deg)
        np.testing.assert_allclose(info["K"], cam.K)
        assert (info["width"], info["height"], info["frame_id"]) == (24, 24, "event_camera")


def test_leave_out_and_adaptive_switches_change_cost_not_events(tmp_path):
    base = dict(duration=0.05, scene_time_offset=0.15, encoding="mono", chunk=0.025)
    on, b1 = publish(tmp_path, "on", **base)
    off, b2 = publish(tmp_path, "off", leave_out=False, **base)
    np.testing.assert_array_equal(read_events(b1, EVENTS).events, read_events(b2, EVENTS).events)
    assert on.rays_rendered < 0.8 * off.rays_rendered          # primitives tested only inside their screen boxes
    # static start: the adaptive sampler takes max-size steps where nothing moves
    still = dict(duration=0.08, scene_time_offset=0.0, encoding="mono", chunk=0.04)
    ad, _ = publish(tmp_path, "ad", adaptive=True, **still)
    fx, _ = publish(tmp_path, "fx", adaptive=False, **still)
    assert ad.events == fx.events == 0
    assert ad.renders * 4 < fx.renders           # 17 renders (10 ms steps + midpoints) against 81


# ----------------------------------------------------------------------------- stability

def test_static_camera_static_scene_gives_no_events(tmp_path):
    rep, bag = publish(tmp_path, duration=0.09, scene_time_offset=0.0, adaptive=True)
    assert rep.events == 0 and rep.messages == 0 and rep.topics["/event_publisher/camera_info"] == 1
    assert read_events(bag, EVENTS).events.size == 0           # the topic is in the bag, empty


def _traj_file(tmp_path, Ts, span_ns):
    t = np.linspace(0, span_ns, len(Ts)).astype(np.int64)
    poses = []
    for ti, T in zip(t, Ts):
        q = matrix_to_quat_ros(T[:3, :3])
        poses.append({"t_ns": int(ti), "position": T[:3, 3].tolist(), "orientation": q.tolist()})
    f = tmp_path / "traj.yaml"
    f.write_text(yaml.safe_dump({"poses": poses}))
    return f


def test_empty_view_and_tiny_resolution(tmp_path):
    sky = look_at([0.0, 0.0, 5.0], [0.0, 0.1, 50.0])           # camera looks up, away from every object
    f = _traj_file(tmp_path, [sky, sky], 50_000_000)
    rep, _ = publish(tmp_path, "sky", trajectory=str(f), scene_time_offset=0.2)
    assert rep.events == 0 and rep.renders > 10
    rep, bag = publish(tmp_path, "tiny", **{"camera.width": 3, "camera.height": 2, "duration": 0.15,
                                            "scene_time_offset": 0.15, "encoding": "mono"})
    ev = read_events(bag, EVENTS).events
    assert rep.events == ev.size > 0 and ev["x"].max() < 3 and ev["y"].max() < 2


def test_very_fast_trajectory(tmp_path):
    scene = load_scene("fork", check_cameras=False)
    ring = scene.camera_poses("train", views=36)
    f = _traj_file(tmp_path, ring + ring[:1], 20_000_000)         # one turn around the scene in 20 ms
    rep, bag = publish(tmp_path, trajectory=str(f), encoding="mono", adaptive=True, min_step_ns=50_000)
    ev = read_events(bag, EVENTS).events
    assert rep.events == ev.size > 1000
    assert np.all(np.diff(ev["t"]) >= 0) and ev["t"][0] > 0 and ev["t"][-1] <= 20_000_000
    assert ev["x"].max() < 24 and ev["y"].max() < 24


# ----------------------------------------------------------------------------- CLI

def test_evdnerf_publish_cli(tmp_path, capsys):
    params = tmp_path / "p.yaml"
    params.write_text(yaml.safe_dump({"event_publisher": {"ros__parameters": {
        "camera": {"width": 20, "height": 16}, "adaptive": False, "realtime_factor": 0.0, "chunk": 0.02}}}))
    out = tmp_path / "out"
    assert main(["publish", "-o", str(out), "--params-file", str(params), "--duration", "0.04",
                 "-p", "scene_time_offset=0.15", "--encoding", "mono", "--json"]) == 0
    import json

    rep = json.loads(capsys.readouterr().out)
    ev = read_events(out, EVENTS).events
    assert rep["events"] == ev.size > 0 and rep["rtf"] > 0 and ev["x"].max() < 20
    assert main(["publish", "-o", str(out), "--duration", "0.01"]) == 2            # exists: refused
    assert "already exists" in capsys.readouterr().err
    assert main(["publish", "--duration", "0.01"]) == 2
    assert main(["publish", "-o", str(tmp_path / "x"), "-p", "c_pos=-1"]) == 2
    assert "c_pos" in capsys.readouterr().err and not (tmp_path / "x").exists()


# ----------------------------------------------------------------------------- trained field source

def test_field_source_occupancy_mask_saves_rays_not_pixels(tmp_path):
    import torch

    from evdnerf_ros.nodes.sources import FieldSource
    from evdnerf_ros.train.checkpoint import save_checkpoint
    from evdnerf_ros.train.config import TrainConfig, field_from_config

    cfg = TrainConfig(backbone="planes")
    torch.manual_seed(1)
    occ = torch.zeros((8, 8, 8), dtype=torch.bool)
    occ[3:5, 3:5, 3:5] = True                         # a small occupied core: most rays cross nothing
    (tmp_path / "run").mkdir()
    save_checkpoint(tmp_path / "run" / "checkpoint.pt", field=field_from_config(cfg), optimizer=None,
                    iteration=0, config=cfg.to_dict(), backbone=cfg.backbone, rng={},
                    box=[[-1, -1, -1], [1, 1, 1]], extra={"occupied": occ})
    cam = PinholeCamera.from_fov(20, 16, 50.0)
    T = look_at([0.0, -3.0, 0.3], [0.0, 0.0, 0.0])
    on = FieldSource(tmp_path / "run", cam, duration_ns=10**9, leave_out=True)
    off = FieldSource(tmp_path / "run", cam, duration_ns=10**9, leave_out=False)
    for t in (0, 500_000_000):
        a, b = on(T, t), off(T, t)
        assert a.shape == (16, 20) and a.dtype == np.float32
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)
    assert on.rays_rendered < 0.5 * off.rays_rendered and off.rays_rendered == off.rays_total == 2 * 320
    poses = [{"t_ns": t, "position": T[:3, 3].tolist(), "orientation": matrix_to_quat_ros(
        T[:3, :3]).tolist()} for t in (0, 20_000_000)]
    (tmp_path / "t.yaml").write_text(yaml.safe_dump({"poses": poses}))
    rep, _ = publish(tmp_path, run_dir=str(tmp_path / "run"), trajectory=str(tmp_path / "t.yaml"),
                     field_duration=0.02, **{"camera.width": 12, "camera.height": 10})
    assert rep.renders == 21 and rep.rays_rendered < rep.rays_total


def test_event_publisher_executable_help_and_errors(capsys):
    from evdnerf_ros.nodes.event_publisher import PARAMETERS
    from evdnerf_ros.nodes.event_publisher import main as exe

    assert exe(["--help"]) == 0
    text = capsys.readouterr().out
    assert all(f"  {s.name} (" in text for s in PARAMETERS)
    assert exe(["--ros-args", "-p", "encoding:=evt4"]) == 2
    assert "parameter 'encoding': 'evt4' is not one of" in capsys.readouterr().err
    assert exe(["stray", "--ros-args"]) == 2
    assert "unexpected arguments ['stray']" in capsys.readouterr().err


def test_a_trained_run_without_trajectory_orbits_its_training_views(tmp_path):
    """`publish --run RUN` alone: the camera the run was trained with, once round its training views."""
    import torch

    from evdnerf_ros.io.messages import intrinsics_from_camera_info
    from evdnerf_ros.train.checkpoint import save_checkpoint
    from evdnerf_ros.train.config import TrainConfig, field_from_config
    from evdnerf_ros.train.run import TrainedRun

    cfg = TrainConfig(backbone="planes")
    torch.manual_seed(1)
    ring = [look_at([3 * np.cos(a), 3 * np.sin(a), 0.5], [0.0, 0.0, 0.0]).tolist()
            for a in np.radians([0, 270, 90, 180])]                  # stored out of azimuth order
    for name, train_set in (("run", {"time_range_ns": [0, 40_000_000], "thresholds": [0.2, 0.2],
                                     "camera": [14, 10, 12.0, 12.0, 6.5, 4.5], "ring": ring}),
                            ("old", {"time_range_ns": [0, 40_000_000], "thresholds": [0.2, 0.2]})):
        (tmp_path / name).mkdir()
        save_checkpoint(tmp_path / name / "checkpoint.pt", field=field_from_config(cfg),
                        optimizer=None, iteration=0, config=cfg.to_dict(), backbone=cfg.backbone, rng={},
                        box=[[-1, -1, -1], [1, 1, 1]], extra={"train_set": train_set})
    t, T = TrainedRun.load(tmp_path / "run").orbit(40_000_000)
    assert t.tolist() == [0, 10_000_000, 20_000_000, 30_000_000, 40_000_000]
    az = np.degrees(np.arctan2(T[:, 1, 3], T[:, 0, 3])) % 360
    assert np.all(np.diff(np.unwrap(np.radians(az))) > 0) and np.array_equal(T[0], T[-1])
    no_size = {"camera.width": 0, "camera.height": 0}
    rep, bag = publish(tmp_path, run_dir=str(tmp_path / "run"), **no_size)
    assert rep.renders > 20
    with open_bag(bag) as b:
        (_, info), *_ = list(b.read_messages([n for n in b.topics if n.endswith("camera_info")][0]))
    got = intrinsics_from_camera_info(info)
    assert (got["width"], got["height"]) == (14, 10) and got["K"][0, 0] == 12.0
    with pytest.raises(EvdnerfError, match="records no ring .* give a trajectory"):
        publish(tmp_path, name="c", run_dir=str(tmp_path / "old"), **{"camera.width": 8, "camera.height": 8})


def test_an_open_ring_is_swept_there_and_back_not_closed_through_the_scene():
    """A turntable's half circle of views (a 180 degree gap): the default orbit goes along the views
    and back, never cutting across the gap (through the scene: the straight line from the last view
    to the first passes 0.5 m from the centre here); a ring spread round is still closed."""
    from evdnerf_ros.geometry.pose_track import PoseTrack
    from evdnerf_ros.train.run import TrainedRun

    def orbit(deg, centre=(0.2, -0.1, 0.3)):
        run = TrainedRun.__new__(TrainedRun)
        run.ring = np.stack([look_at([centre[0] + 3 * np.cos(a), centre[1] + 3 * np.sin(a), 1.0], centre)
                             for a in np.radians(deg)])
        run.checkpoint_path = "run"
        t, T = run.orbit(80_000_000)
        dense = PoseTrack(t, T).poses(np.linspace(0, 80_000_000, 401).astype(np.int64))
        az = np.degrees(np.arctan2(T[:, 1, 3] - centre[1], T[:, 0, 3] - centre[0]))
        return az, np.linalg.norm(dense[:, :2, 3] - np.array(centre[:2]), axis=1)

    az, dist = orbit([120, 0, 180, 30, 90])              # stored out of order
    np.testing.assert_allclose(az, [0, 30, 90, 120, 180, 120, 90, 30, 0], atol=1e-9)
    assert dist.min() > 3 * np.cos(np.radians(30)) - 1e-9          # the widest chord is 60 degrees
    az, dist = orbit([0, 90, 180, 270])                              # spread round: closed
    np.testing.assert_allclose(np.unwrap(np.radians(az)) % (2 * np.pi),
                               np.radians([270, 0, 90, 180, 270]), atol=1e-9)
    az, _ = orbit([0, 120, 240])                                    # three views: still a closed ring
    assert az.size == 4


def test_a_paced_run_that_falls_behind_real_time_says_so_once_with_the_lever(capsys, monkeypatch):
    """realtime_factor > 0 is a schedule: a run more than LATE_WARN_S behind it warns once, naming the
    lever that buys speed for its error; an unpaced run (0) has no schedule to miss."""
    from evdnerf_ros.nodes import event_publisher

    monkeypatch.setattr(event_publisher, "LATE_WARN_S", 0.05)
    slow = {**SMALL, "render_rate_hz": 20000.0, "scene_time_offset": 0.15, "duration": 0.01, "chunk": 0.001,
            "realtime_factor": 400.0}
    rep = run_node((), overrides=slow, dds=False)
    err = capsys.readouterr().err
    assert rep.fell_behind and rep.wall_seconds > 0.05 + 0.01 / 400
    assert err.count("falling behind real time x400") == 1 and "camera.width" in err
    rep = run_node((), overrides={**slow, "realtime_factor": 0.0}, dds=False)
    assert not rep.fell_behind and "falling behind" not in capsys.readouterr().err

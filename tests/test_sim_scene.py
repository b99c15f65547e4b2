"""Scenes as YAML (validation with key paths), trajectories, the servo profile, camera rings."""

import math

import numpy as np
import pytest
import yaml

from evdnerf_ros.errors import InputError
from evdnerf_ros.geometry import servo_profile as sp
from evdnerf_ros.geometry.camera import CameraRing, PinholeCamera, look_at, ring_poses
from evdnerf_ros.sim.scene import list_presets, load_scene, scene_from_dict
from evdnerf_ros.geometry.rotations import (matrix_to_quat, quat_from_axis_angle, quat_from_euler_deg,
                                            quat_log, quat_mul, quat_to_matrix, slerp)
from evdnerf_ros.geometry.trajectory import HermiteSpline, KeyframeTrajectory, RotationSpline

MS = 1_000_000


def minimal(**over):
    d = {"time": {"start_s": 0, "end_s": 1},
         "objects": [{"name": "ball", "type": "sphere", "radius": 0.3}]}
    d.update(over)
    return d


def write(tmp_path, data, name="scene.yaml"):
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data) if not isinstance(data, str) else data)
    return p


# ----------------------------------------------------------------------------- YAML

def test_presets_listed_and_load():
    names = list_presets()
    for n in ("jet-down", "jet-spiral", "jet-land", "multi", "lego", "fork"):
        assert n in names
    sc = load_scene("fork")
    assert sc.name == "fork" and sc.cameras.ring.views == 18
    assert sc.cameras.ring.radius == 4.0 and sc.cameras.ring.validation_offset_deg == 10.0
    assert sc.object("fork").servo is not None
    assert sc.motion_span_ns() == (100 * MS, 1100 * MS)


def test_unknown_preset_lists_allowed():
    with pytest.raises(InputError, match="unknown scene preset 'jet-up'.*jet-down"):
        load_scene("jet-up")


@pytest.mark.parametrize("mutate, path, allowed", [
    (lambda d: d["objects"][0].update(colour=1), "objects[0].colour", "albedo"),
    (lambda d: d.update(camera={}), "camera", "cameras"),
    (lambda d: d["objects"].append({"type": "box", "size": [1, 1, 1],
                                    "motion": {"keyframes": [{"t_s": 0, "pos": [0, 0, 0]}]}}),
     "objects[1].motion.keyframes[0].pos", "position"),
    (lambda d: d.update(lights={"ambient": 0.2, "directional": [{"direction": [0, 0, -1],
                                                                 "power": 1}]}),
     "lights.directional[0].power", "intensity"),
])
def test_unknown_keys_name_path_and_allowed(tmp_path, mutate, path, allowed):
    d = minimal()
    mutate(d)
    p = write(tmp_path, d)
    with pytest.raises(InputError) as e:
        load_scene(p)
    msg = str(e.value)
    assert str(p) in msg and path in msg and allowed in msg


def test_bad_type_and_texture_list_allowed(tmp_path):
    d = minimal()
    d["objects"][0]["type"] = "cone"
    with pytest.raises(InputError, match=r"objects\[0\]\.type: expected one of box, sphere, cylinder.*, got 'cone'"):
        load_scene(write(tmp_path, d))
    d = minimal()
    d["objects"][0]["texture"] = {"type": "plaid", "scale": 1}
    with pytest.raises(InputError, match=r"objects\[0\]\.texture\.type.*checker, stripes, noise"):
        load_scene(write(tmp_path, d))
    d = minimal()
    d["objects"][0]["texture"] = {"type": "checker", "scale": 1, "seed": 3}
    with pytest.raises(InputError, match=r"objects\[0\]\.texture\.seed.*unknown key"):
        load_scene(write(tmp_path, d))


@pytest.mark.parametrize("obj, path", [
    ({"type": "sphere", "radius": float("nan")}, "objects[0].radius"),
    ({"type": "sphere", "radius": -1}, "objects[0].radius"),
    ({"type": "box", "size": [1, 0, 1]}, "objects[0].size[1]"),
    ({"type": "box", "size": [1, 1]}, "objects[0].size"),
    ({"type": "ellipsoid", "radii": [1, 1, float("inf")]}, "objects[0].radii[2]"),
    ({"type": "sphere", "radius": 0.2, "albedo": 0}, "objects[0].albedo"),
    ({"type": "cylinder", "radius": 0.2, "height": "tall"}, "objects[0].height"),
])
def test_bad_numbers(tmp_path, obj, path):
    p = write(tmp_path, minimal(objects=[obj]))
    with pytest.raises(InputError) as e:
        load_scene(p)
    assert str(p) in str(e.value) and path in str(e.value)


def test_keyframe_times_must_increase(tmp_path):
    d = minimal()
    d["objects"][0]["motion"] = {"keyframes": [
        {"t_s": 0.0, "position": [0, 0, 0]}, {"t_s": 0.5, "position": [0, 0, 1]},
        {"t_s": 0.5, "position": [0, 0, 0]}]}
    with pytest.raises(InputError, match=r"objects\[0\]\.motion\.keyframes\[2\]\.t_s.*"
                                         "strictly increasing"):
        load_scene(write(tmp_path, d))
    d["objects"][0]["motion"]["keyframes"][2] = {"t_s": 0.7}
    with pytest.raises(InputError, match=r"keyframes\[2\].*'position'"):
        load_scene(write(tmp_path, d))


def test_time_range_and_exact_times(tmp_path):
    with pytest.raises(InputError, match="time.end_s"):
        load_scene(write(tmp_path, minimal(time={"start_s": 1, "end_s": 1})))
    d = minimal(time={"start_s": 0.1, "end_s": "1300ms"})
    d["objects"][0]["motion"] = {"keyframes": [{"t_s": 0.1, "position": [0, 0, 0]},
                                               {"t_s": 0.3, "position": [0, 0, 1]}]}
    sc = load_scene(write(tmp_path, d))
    assert (sc.start_ns, sc.end_ns) == (100_000_000, 1_300_000_000)
    assert sc.object("ball").motion.times_ns.tolist() == [100_000_000, 300_000_000]


def test_hinge_validation(tmp_path):
    d = minimal()
    d["objects"].append({"name": "arm", "type": "box", "size": [1, 0.1, 0.1],
                         "motion": {"hinge": {"parent": "nothing", "axis": [0, 1, 0],
                                              "angle_keyframes": [{"t_s": 0, "angle_deg": 0}]}}})
    with pytest.raises(InputError, match=r"objects\[1\]\.motion\.hinge\.parent.*'nothing'"):
        load_scene(write(tmp_path, d))
    d["objects"][1]["motion"]["hinge"]["parent"] = "ball"
    d["objects"][1]["motion"]["hinge"]["axis"] = [0, 0, 0]
    with pytest.raises(InputError, match=r"hinge\.axis.*zero"):
        load_scene(write(tmp_path, d))
    d["objects"][1]["motion"]["hinge"]["axis"] = [0, 1, 0]
    d["objects"][1]["motion"]["hinge"]["servo"] = {"profile": "run"}
    with pytest.raises(InputError, match="exactly one of angle_keyframes, servo"):
        load_scene(write(tmp_path, d))
    del d["objects"][1]["motion"]["hinge"]["angle_keyframes"]
    d["objects"][1]["motion"]["hinge"]["servo"] = {"profile": "wiggle"}
    with pytest.raises(InputError, match=r"servo\.profile.*run, move"):
        load_scene(write(tmp_path, d))


def test_hinged_child_follows_parent_and_angle():
    d = minimal(objects=[
        {"name": "base", "type": "box", "size": [0.2, 0.2, 0.2],
         "motion": {"keyframes": [{"t_s": 0, "position": [0, 0, 0]},
                                  {"t_s": 1, "position": [1, 0, 0]}]}},
        {"name": "arm", "type": "box", "size": [0.5, 0.05, 0.05],
         "pose": {"position": [0.35, 0, 0]},
         "motion": {"hinge": {"parent": "base", "axis": [0, 0, 1], "pivot": [0.1, 0, 0],
                              "angle_keyframes": [{"t_s": 0, "angle_deg": 0},
                                                  {"t_s": 1, "angle_deg": 90}]}}}])
    sc = scene_from_dict(d, check_cameras=False)
    T = sc.transforms(1_000_000_000)["arm"]
    # base moved to x=1; the arm turned 90 deg about z through (1.1, 0, 0)
    assert np.allclose(T[:3, 3], [1.1, 0.25, 0.0], atol=1e-12)
    assert np.allclose(T[:3, :3], quat_to_matrix(quat_from_axis_angle([0, 0, 1], math.pi / 2)))


def test_broken_yaml_and_missing_mesh(tmp_path):
    p = write(tmp_path, "objects: [ {type: box, size: [1, 1, 1]\n")
    with pytest.raises(InputError, match=f"{p}.*line.*not valid YAML"):
        load_scene(p)
    d = minimal(objects=[{"type": "mesh", "path": "missing.obj"}])
    with pytest.raises(InputError, match=r"objects\[0\]\.path.*missing\.obj.*not found"):
        load_scene(write(tmp_path, d))


def test_empty_and_broken_meshes(tmp_path):
    pytest.importorskip("trimesh")
    (tmp_path / "empty.obj").write_text("# nothing here\n")
    (tmp_path / "broken.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\n"
                                          b"element vertex 3\nproperty float x\nend_header\n\x00")
    for name in ("empty.obj", "broken.ply"):
        p = write(tmp_path, minimal(objects=[{"type": "mesh", "path": name}]))
        with pytest.raises(InputError) as e:
            load_scene(p)
        assert str(p) in str(e.value) and name in str(e.value)


def test_camera_inside_object(tmp_path):
    d = minimal(objects=[{"name": "wall", "type": "box", "size": [0.5, 10, 10],
                          "pose": {"position": [4, 0, 0]}}])
    p = write(tmp_path, d)
    with pytest.raises(InputError, match=f"{p}.*training view 0 .*inside object 'wall'"):
        load_scene(p)
    # a moving object that sweeps through a validation camera later on
    d = minimal()
    d["objects"][0]["motion"] = {"keyframes": [
        {"t_s": 0, "position": [0, 0, 0]},
        {"t_s": 1, "position": [4 * math.cos(math.radians(30)) * math.cos(math.radians(20)),
                                4 * math.sin(math.radians(30)) * math.cos(math.radians(20)),
                                4 * math.sin(math.radians(20))]}]}
    with pytest.raises(InputError, match="validation view 1 .*inside object 'ball'"):
        load_scene(write(tmp_path, d))


# ----------------------------------------------------------------------------- trajectories

def _knots():
    t = np.array([0, 300, 450, 1000], dtype=np.int64) * MS
    pos = np.array([[0, 0, 1], [0.5, 0.2, 0.4], [0.6, -0.1, 0.0], [1.0, 0.3, -0.8]])
    q = np.stack([quat_from_euler_deg(e) for e in
                  [(0, 0, 0), (10, 30, 80), (40, -10, 150), (0, 20, 230)]])
    return t, pos, q


def test_interpolation_passes_through_keyframes():
    t, pos, q = _knots()
    tr = KeyframeTrajectory(t, pos, q)
    for k in range(len(t)):
        assert np.abs(tr.position(t[k]) - pos[k]).max() < 1e-12
        assert min(np.abs(tr.rotation(t[k]) - q[k]).max(),
                   np.abs(tr.rotation(t[k]) + q[k]).max()) < 1e-12
    # held outside the span
    assert np.allclose(tr.position(-5 * MS), pos[0])
    assert np.allclose(tr.position(2000 * MS), pos[-1])


def _kink(f, tk, h=1000):
    left = (np.asarray(f(tk)) - np.asarray(f(tk - h))) / h
    right = (np.asarray(f(tk + h)) - np.asarray(f(tk))) / h
    return np.abs(left - right).max() / np.abs(left).max()


def test_interpolation_is_c1():
    t, pos, q = _knots()
    hp, rs = HermiteSpline(t, pos), RotationSpline(t, q)
    for tk in t[1:-1]:
        assert _kink(hp, int(tk)) < 1e-3
        assert _kink(rs, int(tk)) < 1e-3
    # the check detects a kink: piecewise slerp is only C0
    def piecewise_slerp(tt):
        k = int(np.searchsorted(t, tt, side="right")) - 1
        k = min(k, len(t) - 2)
        qa, qb = q[k], q[k + 1] if np.dot(q[k], q[k + 1]) >= 0 else -q[k + 1]
        return slerp(qa, qb, (tt - t[k]) / (t[k + 1] - t[k]))
    assert _kink(piecewise_slerp, int(t[1])) > 1e-2


def test_slerp_unit_and_endpoints():
    q0 = quat_from_euler_deg((10, 20, 30))
    q1 = quat_from_euler_deg((-40, 60, 170))
    u = np.linspace(0, 1, 101)
    qs = slerp(q0, q1, u)
    assert np.allclose(np.linalg.norm(qs, axis=1), 1.0, atol=1e-14)
    assert np.allclose(qs[0], q0)
    assert min(np.abs(qs[-1] - q1).max(), np.abs(qs[-1] + q1).max()) < 1e-12
    ang = np.linalg.norm(quat_log(quat_mul(q0 * [1, -1, -1, -1], qs)), axis=1)
    assert np.allclose(np.diff(ang), ang[-1] / 100, atol=1e-12)       # constant angular speed
    # a two-keyframe rotation spline is slerp
    rs = RotationSpline([0, 1000], np.stack([q0, q1]))
    assert np.allclose(rs(250), slerp(q0, q1, 0.25), atol=1e-14)


def test_euler_and_matrix_conventions():
    R = quat_to_matrix(quat_from_euler_deg((90, 0, 0)))
    assert np.allclose(R @ [0, 1, 0], [0, 0, 1])
    R = quat_to_matrix(quat_from_euler_deg((30, 40, 50)))
    Rx = quat_to_matrix(quat_from_axis_angle([1, 0, 0], math.radians(30)))
    Ry = quat_to_matrix(quat_from_axis_angle([0, 1, 0], math.radians(40)))
    Rz = quat_to_matrix(quat_from_axis_angle([0, 0, 1], math.radians(50)))
    assert np.allclose(R, Rz @ Ry @ Rx)
    assert np.allclose(quat_to_matrix(matrix_to_quat(R)), R)


# ----------------------------------------------------------------------------- servo

def test_servo_move_ends_and_monotone():
    D = 400 * MS
    e = np.arange(0, D + 1, 397_001)
    a = sp.move_angle_deg(e, D, 30.0, 120.0)
    assert a[0] == 30.0 and sp.move_angle_deg(D, D, 30.0, 120.0) == 120.0
    assert np.all(np.diff(a) > 0)
    # zero velocity at both ends (finite differences over 1 us)
    v0 = (sp.move_angle_deg(1000, D, 30, 120) - 30) / 1e-6
    v1 = (120 - sp.move_angle_deg(D - 1000, D, 30, 120)) / 1e-6
    assert abs(v0) < 1e-3 and abs(v1) < 1e-3
    cmd = [sp.move_command_mdeg(int(x) // 1000, D // 1000, 30_000, 120_000) for x in e]
    assert cmd[0] == 30_000
    assert sp.move_command_mdeg(D // 1000, D // 1000, 30_000, 120_000) == 120_000
    assert np.all(np.diff(cmd) >= 0)


def test_servo_integer_mirror_is_monotone_everywhere_and_close():
    s = sp.min_jerk_q16_from_u(np.arange(sp.ONE_Q16 + 1))
    assert s[0] == 0 and s[-1] == sp.ONE_Q16 and np.all(np.diff(s) >= 0)
    u = np.arange(sp.ONE_Q16 + 1) / sp.ONE_Q16
    assert np.abs(s / sp.ONE_Q16 - sp.min_jerk(u)).max() < 1.1 / sp.ONE_Q16
    run = sp.DEFAULT_RUN
    e = np.arange(0, run.duration_ns + 1, 1_234_567)
    cmd = np.array([run.command_mdeg(int(x)) for x in e]) / 1000.0
    assert np.abs(cmd - run.angle_deg(e)).max() < 0.01 + 90 * 2.0 ** -14


def test_run_profile_segments_and_repeatability():
    run = sp.DEFAULT_RUN
    assert run.duration_ns == 1000 * MS
    b = run.boundaries_ns
    assert [run.angle_deg(int(x)) for x in b] == [90.0, 135.0, 45.0, 90.0]
    assert [run.command_mdeg(int(x)) for x in b] == [90_000, 135_000, 45_000, 90_000]
    assert all(run.velocity_deg_s(int(x)) == 0.0 for x in b)
    assert run.angle_deg(-5) == 90.0 and run.angle_deg(run.duration_ns + 10**9) == 90.0
    # repeatable to the ns: the same elapsed time gives the same angle for any RUN start
    from evdnerf_ros.sim.scene import ServoDrive
    e = np.arange(0, run.duration_ns, 9_999_991)
    for start in (0, 123_456_789, 10_000 * 10**9 + 7):
        drive = ServoDrive(run, start, 90.0)
        got = [drive.angle_rad(start + int(x)) for x in e]
        assert got == [math.radians(run.angle_deg(int(x)) - 90.0) for x in e]
    with pytest.raises(InputError, match="millidegree"):
        sp.RunProfile(90, ((45.0001, 100),))
    with pytest.raises(InputError, match="1..65535"):
        sp.RunProfile(90, ((45, 0),))


# ----------------------------------------------------------------------------- cameras

def test_camera_ring_geometry():
    ring = CameraRing(views=18, radius=4.0, elevation_deg=20.0, look_at=(0.1, -0.2, 0.3),
                      validation_offset_deg=10.0)
    train, val = ring.poses("train"), ring.poses("val")
    assert len(train) == 18 and len(val) == 18
    c = np.array(ring.look_at)
    for T in train + val:
        R = T[:3, :3]
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)
        p = T[:3, 3]
        assert np.isclose(np.linalg.norm(p - c), 4.0)
        assert np.allclose(R[:, 2], (c - p) / np.linalg.norm(c - p), atol=1e-12)  # axis -> look-at
        assert abs(R[2, 0]) < 1e-12 and R[2, 1] < 0                 # no roll, y points down
        assert np.isclose(np.degrees(np.arcsin((p - c)[2] / 4.0)), 20.0)
    az = lambda T: np.degrees(np.arctan2(*(T[:3, 3] - c)[1::-1]))
    steps = [(az(train[(k + 1) % 18]) - az(train[k])) % 360 for k in range(18)]
    assert np.allclose(steps, 20.0)
    assert np.allclose([(az(v) - az(t)) % 360 for t, v in zip(train, val)], 10.0)
    # the look-at point projects to the principal point
    cam = PinholeCamera.from_fov(65, 49, 40.0)
    for T in train[:3]:
        pc = (c - T[:3, 3]) @ T[:3, :3]
        assert np.allclose(cam.project(pc[None])[0], [cam.cx, cam.cy])


def test_camera_errors_and_rays():
    with pytest.raises(InputError, match="elevation"):
        ring_poses(4, 4.0, 90.0)
    with pytest.raises(InputError):
        look_at([0, 0, 0], [0, 0, 0])
    cam = PinholeCamera.from_fov(8, 6, 90.0)
    assert np.isclose(cam.fx, 4.0) and (cam.cx, cam.cy) == (3.5, 2.5)
    d = cam.ray_directions(2)
    assert d.shape == (12, 16, 3) and np.allclose(np.linalg.norm(d, axis=-1), 1.0)
    # the mean of a pixel's sub-sample offsets is the pixel centre
    assert np.isclose(((d[:, :, 0] / d[:, :, 2])[:2, :2]).mean(), (0 - cam.cx) / cam.fx)
    assert np.isclose(cam.resized(16, 12).fx, 8.0) and cam.resized(16, 12).cx == 7.5

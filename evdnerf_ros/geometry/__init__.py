"""Geometry shared by the simulator, training, evaluation, the publisher and the rig: pinhole
cameras and camera rings, rigid poses (one rigidity check, one monotonic-times check),
rotations (quaternions in one order, ``(w, x, y, z)``; ROS's ``(x, y, z, w)`` only at the
message boundary), keyframe trajectories, pose tracks and the servo's motion profile."""

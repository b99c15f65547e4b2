"""Camera calibration from events of a ChArUco board (issue 15, item 5).

- :mod:`.board`: the board (default 7 x 5 squares of 30 mm, DICT_5X5_100), its picture;
- :mod:`.images`: board images from events (blinking board bursts, or edge windows);
- :mod:`.detect`: ChArUco corners, blinks at one pose merged into one view;
- :mod:`.intrinsics`: K and distortion (``cv2.calibrateCamera``);
- :mod:`.extrinsics`: a view's ``T_world_cam`` from the board at the rig's origin;
- :mod:`.run`: the `evdnerf calibrate` job (calibration YAML, session.yaml update).

OpenCV (opencv-contrib-python-headless) is imported only when a board is used.
"""

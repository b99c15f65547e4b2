"""Hardware side of the toolkit: servo client, USB camera drivers, capture, sync, flashing.

Imports go one way only: rig -> evdnerf_ros, never the reverse.
"""

"""EvDNeRF toolkit: event-camera data, simulation and learned event simulators (ROS 2 style)."""

__version__ = "0.1.0"

"""Long-running nodes built on :mod:`evdnerf_ros.ros` (the event publisher, the echo tool)."""

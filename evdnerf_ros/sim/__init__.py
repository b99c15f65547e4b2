"""Simulation: the exact ESIM-style event generator, time sampling of any renderer,
the project-wide log rule and video2events.

    from evdnerf_ros.sim import EventGenerator, simulate_renderer, video_to_events
"""

from .generator import EventGenerator, generate_events
from ..events.logmap import LOG_EPS, check_intensity, intensity_from_log, log_intensity
from .noise import MIN_THRESHOLD
from .sampling import SamplingStats, simulate_renderer
from .video import GAMMA_8BIT, linearize_8bit, load_frames_npz, run_video2events, video_to_events

__all__ = [
    "EventGenerator", "generate_events", "LOG_EPS", "log_intensity", "intensity_from_log",
    "check_intensity", "MIN_THRESHOLD", "SamplingStats", "simulate_renderer", "GAMMA_8BIT",
    "linearize_8bit", "load_frames_npz", "run_video2events", "video_to_events",
]

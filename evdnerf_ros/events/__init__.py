"""Event core: the event dtype, validation, time slicing, accumulation, images and rates."""

from .accumulate import (counts_from_log_change, log_change_image, log_change_stack,
                         polarity_counts, signed_counts)
from .images import event_image, save_png, signed_to_rgb
from .rate import event_rate, plot_event_rate
from .slicing import time_slice, window_edges, window_indices, window_of_each_event
from .types import (EVENT_DTYPE, MAX_SENSOR_SIZE, TRIGGER_DTYPE, as_events, empty_events,
                    empty_triggers, make_events, make_triggers, sort_events, validate_events)

__all__ = [
    "EVENT_DTYPE", "TRIGGER_DTYPE", "MAX_SENSOR_SIZE", "as_events", "empty_events",
    "empty_triggers", "make_events", "make_triggers", "sort_events", "validate_events",
    "time_slice", "window_edges", "window_indices", "window_of_each_event",
    "polarity_counts", "signed_counts", "log_change_image", "log_change_stack",
    "counts_from_log_change", "event_image", "signed_to_rgb", "save_png",
    "event_rate", "plot_event_rate",
]

"""EvDNeRF training: config, ray sampler, event losses, the loop and checkpoints.

``run_train(train_h5, run_dir, ...)`` is the ``evdnerf train`` entry point;
``TrainedRun.load(run_dir)`` reads a run folder back (evaluation, publishing, resuming).
"""

from .checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from .config import TrainConfig, resolve_config
from .run import TrainedRun
from .losses import bin_bounds, bin_loss, mse_loss, no_event_hinge
from .rays import RayBatch, RaySampler, default_box
from .trainer import Trainer, TrainingDivergedError, plane_regularisers, run_train

__all__ = ["TrainConfig", "resolve_config", "bin_bounds", "bin_loss", "mse_loss", "no_event_hinge",
           "RayBatch", "RaySampler", "default_box", "Trainer",
           "TrainingDivergedError", "plane_regularisers", "run_train", "CheckpointError",
           "load_checkpoint", "save_checkpoint", "TrainedRun"]

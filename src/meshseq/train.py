"""``meshseq.train``: the names of ``meshseq.training`` where scripts and tests have always found them.

The code lives in ``meshseq.training`` (one module per concept: config and recipes, data,
losses, optimiser, run folder and processes, the loop); see that package's docstring.
"""

from meshseq.device import resolve_device
from meshseq.training.config import (EMA_WARMUP, FC_LRS, FC_REFERENCE_FAN_IN, FEEDBACK_GRADS, GRAD_CLIP_HISTORY,
                                     GRAD_CLIP_WARMUP, KL_REFERENCE_VERTICES, KL_SCALES, LEGACY_TRAIN_DEFAULTS,
                                     PRECISIONS, RECIPE_OPTIONS, RECIPES, STEP_SCALES, WINDOW_FITS, TrainConfig,
                                     config_from_toml, fc_lr_factor, is_positive_integer)
from meshseq.training.data import (TrainingData, fit_window, gather_frames, load_training_data, step_spread,
                                   training_windows)
from meshseq.training.losses import (WindowLoss, encoder_grad_scale, has_backward_chains, kl_divergence, kl_weight,
                                     latent_health, latent_spread, make_vertex_loss, motion_loss, output_frame_errors,
                                     reconstructed_vertices, squared_norm, window_losses)
from meshseq.training.loop import COLLAPSE_AFTER, collapse_warning, train, validation_scorer
from meshseq.training.optim import (autocast, average_decay, clip_threshold, copy_weights, divergence, fused_adam,
                                    grad_norm, parameter_groups, scale_gradients, update_average, weights_swapped)
from meshseq.training.run import (METRIC_FIELDS, Dist, Metrics, freeze_setup_objects, init_distributed,
                                  remove_run_outputs, resume_meta, resume_point)

__all__ = [
    "COLLAPSE_AFTER", "Dist", "EMA_WARMUP", "FC_LRS", "FC_REFERENCE_FAN_IN", "FEEDBACK_GRADS", "GRAD_CLIP_HISTORY",
    "GRAD_CLIP_WARMUP", "KL_REFERENCE_VERTICES", "KL_SCALES", "LEGACY_TRAIN_DEFAULTS", "METRIC_FIELDS", "Metrics",
    "PRECISIONS", "RECIPES", "RECIPE_OPTIONS", "STEP_SCALES", "TrainConfig", "TrainingData", "WINDOW_FITS",
    "WindowLoss", "autocast", "average_decay", "clip_threshold", "collapse_warning", "config_from_toml",
    "copy_weights", "divergence", "encoder_grad_scale", "fc_lr_factor", "fit_window", "freeze_setup_objects",
    "fused_adam", "gather_frames", "grad_norm", "has_backward_chains", "init_distributed", "is_positive_integer",
    "kl_divergence", "kl_weight", "latent_health", "latent_spread", "load_training_data", "make_vertex_loss",
    "motion_loss", "output_frame_errors", "parameter_groups", "reconstructed_vertices", "remove_run_outputs",
    "resolve_device", "resume_meta", "resume_point", "scale_gradients", "squared_norm", "step_spread", "train",
    "training_windows", "update_average", "validation_scorer", "weights_swapped", "window_losses",
]

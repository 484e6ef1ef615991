"""ACAP (as-consistent-as-possible) deformation features and their inverse (method.md 1-2).

- ``extract``: vertices ``(T, V, 3)`` -> features ``(T, V, 9)`` against a reference mesh.
- ``Reconstructor``: features -> vertices by one factored sparse solve for all frames (and a
  differentiable torch version); ``ExactEncoder``: the exact (minimum-norm corrected) encoding.
- ``Scaling``: the fitted map of features to [-0.95, 0.95] and back.
"""

from meshseq.acap.features import (
    FEATURE_DIM,
    extract,
    extract_gradients,
    features_to_gradients,
    gradients_to_features,
)
from meshseq.acap.gradients import GradientOperator
from meshseq.acap.reconstruct import ExactEncoder, Reconstructor
from meshseq.acap.rotations import CONSISTENCY_MODES, DEFAULT_CONSISTENCY
from meshseq.acap.scaling import Scaling

__all__ = [
    "CONSISTENCY_MODES",
    "DEFAULT_CONSISTENCY",
    "ExactEncoder",
    "FEATURE_DIM",
    "GradientOperator",
    "Reconstructor",
    "Scaling",
    "extract",
    "extract_gradients",
    "features_to_gradients",
    "gradients_to_features",
]

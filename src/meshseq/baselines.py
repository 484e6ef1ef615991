"""The comparisons of the paper's tables: simple extrapolations, interpolation and a mesh VAE.

Prediction baselines take given frames ``(B, U, V, 9)`` and return ``(B, n, V, 9)`` (scaled or
raw features: every map here is affine-equivariant, so both give the same result):

- ``zero_velocity``: repeat the last given frame (hard to beat at short range);
- ``linear_acap``: extrapolate the ACAP features linearly from the last two given frames
  (Gao et al. 2017; with one given frame it equals zero velocity);
- ``vae_latent``: extrapolate linearly in the latent space of a mesh VAE trained on the same
  features. It stands in for Tan et al. (CVPR 2018), which used another feature: outputs say so.

Completion baseline: ``linear_interpolation`` of ACAP features between two keys (CMA-ES is in
``meshseq.synthesize.complete_cma``).
"""

from __future__ import annotations

import numpy as np

PREDICTION_METHODS = ("ours", "zero_velocity", "linear_acap", "vae_latent")
#: ``ours``: the two chains joined by meshseq's default (``synthesize.corrected_crossfade``);
#: ``stitch``: the same chains joined as in the paper (``synthesize.stitch_chains``); ``linear``:
#: interpolation of the keys' ACAP features; ``linear_vertices``: straight lines between the keys'
#: vertex positions.
COMPLETION_METHODS = ("ours", "corrected", "stitch", "cma", "linear", "linear_vertices")
#: the mesh VAE's names, defined in ``meshseq.vae_baseline`` (torch) and read through this module
#: when first used, so that the numpy baselines import without torch
_VAE_NAMES = ("MeshVAE", "vae_param_groups", "train_vae", "vae_latent", "save_vae", "load_vae", "VAE_FC_LR",
              "VAE_NOTE")


def __getattr__(name: str):
    if name in _VAE_NAMES:
        from meshseq import vae_baseline

        return getattr(vae_baseline, name)
    raise AttributeError(f"module 'meshseq.baselines' has no attribute {name!r}")


def zero_velocity(given: np.ndarray, n_frames: int) -> np.ndarray:
    """``(B, U, V, C)`` -> ``(B, n, V, C)``: the last given frame, repeated."""
    g = np.asarray(given)
    return np.repeat(g[:, -1:], n_frames, axis=1)


def linear_acap(given: np.ndarray, n_frames: int) -> np.ndarray:
    """``(B, U, V, C)`` -> ``(B, n, V, C)``: ``X_last + k (X_last - X_prev)``, k = 1..n."""
    g = np.asarray(given)
    if g.shape[1] < 2:
        return zero_velocity(g, n_frames)
    velocity = g[:, -1] - g[:, -2]
    k = np.arange(1, n_frames + 1, dtype=g.dtype)[None, :, None, None]
    return g[:, -1:] + k * velocity[:, None]


def linear_interpolation(key_a: np.ndarray, key_b: np.ndarray, n_between: int) -> np.ndarray:
    """``(V, C)``, ``(V, C)`` -> ``(n_between + 2, V, C)`` from key a to key b, keys included."""
    s = np.linspace(0.0, 1.0, n_between + 2)[:, None, None]
    return (1 - s) * np.asarray(key_a)[None] + s * np.asarray(key_b)[None]


def pairwise_diversity(samples: np.ndarray) -> float:
    """Mean distance between every pair of samples ``(K, ...)`` (per-vertex Euclidean over the last
    axis, averaged); 0 for a single sample.

    On coordinate-major rows ``(D, K, N)``, with no ``norm`` temporaries (8 crane completions of 33
    frames: 0.35 -> 0.12 s; threads over the samples were slower on 2 cores)."""
    k = len(samples)
    if k < 2:
        return 0.0
    x = np.asarray(samples, dtype=np.float64)
    cols = np.ascontiguousarray(np.moveaxis(x.reshape(k, -1, x.shape[-1]), -1, 0))  # (D, K, N)
    total = 0.0
    for i in range(k - 1):  # K is small (a handful of samples)
        sq = np.square(cols[0, i + 1:] - cols[0, i])
        for c in range(1, cols.shape[0]):
            d = np.subtract(cols[c, i + 1:], cols[c, i])
            sq += np.square(d, out=d)
        total += float(np.sqrt(sq, out=sq).sum() / cols.shape[2])
    return total / (k * (k - 1) // 2)

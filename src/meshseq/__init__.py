"""meshseq: learn 3D mesh animation sequences and synthesize new ones.

Implements "Learning Bidirectional LSTM Networks for Synthesizing 3D Mesh Animation
Sequences" (Qiao, Gao, Lai, Xia, AAAI 2019): ACAP deformation features, a mesh-convolutional
VAE feeding a shared-weight bidirectional LSTM, and synthesis by prediction and completion.
"""

from meshseq.errors import MeshseqError, MeshseqWarning

__version__ = "0.1.0"
__all__ = ["MeshseqError", "MeshseqWarning", "__version__"]


def __getattr__(name: str):
    # ``meshseq.load`` imports torch only when first used, so ``import meshseq`` stays light.
    if name == "load":
        from meshseq.api import load

        return load
    raise AttributeError(f"module 'meshseq' has no attribute {name!r}")

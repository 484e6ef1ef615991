"""The torch generator (``meshseq.model.BDLSTM``) behind the interface synthesis runs on: numpy arrays
in and out, as ``meshseq.numpy_net.NumpyNet`` takes and gives them.

The interface (both classes): ``config``; ``initial_state(n_forward, n_backward) -> (h, c)``, each
``(K, B, L)`` float32; ``step(state, x (B, V, C), n_forward=None, sample=False) -> (state', x')``;
``encode(x (B, V, C)) -> mu (B, L)``;
``rollout(first (B, V, C), steps, state, n_forward=None) -> (frames (B, steps + 1, V, C), state')``.
Rows ``[:n_forward]`` are forward chains, the rest backward ones (std-bd's second LSTM). On CPU the
arrays are shared with the tensors (no copies); on CUDA each call moves its inputs and outputs.
"""

from __future__ import annotations

import numpy as np
import torch


class TorchNet:
    """``BDLSTM`` ``net`` on ``device`` (eval mode, no gradients) with numpy at its boundary."""

    def __init__(self, net, device):
        self.net = net
        self.config = net.config
        self.device = torch.device(device)

    def _in(self, x) -> torch.Tensor:
        a = np.asarray(x, dtype=np.float32)
        if not a.flags.writeable:  # (a broadcast key: torch shares only writable memory)
            a = a.copy()
        return torch.from_numpy(a).to(self.device)

    @staticmethod
    def _out(t: torch.Tensor) -> np.ndarray:
        return t.detach().cpu().numpy()

    def initial_state(self, n_forward: int, n_backward: int = 0):
        h, c = self.net.initial_state(n_forward, n_backward)
        return h.numpy(), c.numpy()

    def step(self, state, x, n_forward: int | None = None, sample: bool = False):
        with torch.no_grad():
            st, nxt, _, _ = self.net.step(tuple(self._in(s) for s in state), self._in(x), sample=sample,
                                          n_forward=n_forward)
        return tuple(self._out(s) for s in st), self._out(nxt)

    def encode(self, x) -> np.ndarray:
        with torch.no_grad():
            return self._out(self.net.encode(self._in(x))[0])

    def rollout(self, first, steps: int, state, n_forward: int | None = None):
        with torch.no_grad():
            frames, _, _, st = self.net.rollout(self._in(first), int(steps), tuple(self._in(s) for s in state),
                                                n_forward=n_forward)
        return self._out(frames), tuple(self._out(s) for s in st)

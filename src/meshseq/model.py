"""The BD-LSTM generator: mesh convolution, tied VAE encoder/decoder, recurrent step G(s, X).

Shapes: B windows (batch), V vertices, C = 9 feature channels, L latent width (= LSTM width),
K LSTM layers, n frames of a window.

How one step works (``BDLSTM.step``), for a batch of current frames ``X_t`` ``(B, V, 9)``::

    e      = FC(flatten(Conv3(Conv2(Conv1(X_t)))))            # (B, L)   conv: tanh, FC: linear
    mu     = FC_mu(e),  logvar = FC_logvar(e)                  # (B, L)   the VAE head
    z      = mu + exp(logvar / 2) * eps   (training, eps ~ N(0, I));  z = mu  (evaluation)
    h, s'  = LSTM(z, s)                                        # h: top layer's output (B, L)
    dX     = tConv1(tConv2(tConv3(unflatten(FC^T h + b_d))))   # (B, V, 9)
    X_t+1  = X_t + dX

so the LSTM input is z sampled from the VAE head of the current frame, its top-layer output h goes
through the tied decoder, and the decoder's output is the change of the frame. The decoder FC is
the encoder FC's weight transposed (``FC^T``, own bias); the decoder convolutions reuse the
encoder convolution weights in reverse order, transposed (layer k of the decoder uses
``W1^T, W2^T`` of encoder layer K-1-k), with their own biases; tanh after every decoder layer
except the last, which is linear so that dX can take any sign and size.

Free-running roll-out (training and prediction): a chain sees only its first frame; every later
step encodes the chain's own previous prediction. State ``s = (h, c)``, each ``(K, B, L)``,
starts at +0.1 for the forward chain and -0.1 for the backward chain (every layer, h and c).

Variants (``ModelConfig.variant``):
    ``bd``      one generator for both chains (shared weights); forward windows and time-reversed
                windows are stacked along the batch and run in one pass;
    ``std-bd``  the standard bidirectional LSTM: two LSTMs with their own weights, one per
                direction (the encoder/decoder, a per-frame feature map, stay shared); still one
                batched pass for the encoder/decoder;
    ``uni``     the forward chain only (no backward chain, no L_bd).

Mesh convolution (paper Eq. 2): ``y_i = W1 x_i + W2 mean_{j in N(i)} x_j + b``, the 1-ring mean
by a padded gather (``conv_impl="gather"``) or a row-normalised sparse matrix (``"sparse"``).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import asdict, dataclass, fields

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from meshseq.errors import MeshseqError
from meshseq.mesh import Topology

VARIANTS = ("bd", "std-bd", "uni")
CONV_IMPLS = ("gather", "sparse")


@dataclass
class ModelConfig:
    """Architecture of the generator; stored in every checkpoint's JSON.

    ``latent`` is both the VAE latent width and the LSTM width (the decoder FC is the encoder FC
    transposed, so the LSTM output must have the latent width).
    """

    n_vertices: int
    channels: int = 9
    conv_layers: int = 3
    latent: int = 128
    lstm_layers: int = 3
    variant: str = "bd"
    conv_impl: str = "sparse"
    init_state: float = 0.1

    def __post_init__(self):
        if self.variant not in VARIANTS:
            raise MeshseqError(f"--variant {self.variant!r}: expected one of {', '.join(VARIANTS)}")
        if self.conv_impl not in CONV_IMPLS:
            raise MeshseqError(f"--conv {self.conv_impl!r}: expected one of {', '.join(CONV_IMPLS)}")
        for name in ("n_vertices", "channels", "conv_layers", "latent", "lstm_layers"):
            if int(getattr(self, name)) < 1:
                raise MeshseqError(f"model option {name}={getattr(self, name)} must be at least 1")

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> "ModelConfig":
        known = {f.name for f in fields(ModelConfig)}
        unknown = set(d) - known
        if unknown:
            raise MeshseqError(f"model config has unknown keys {sorted(unknown)} (newer meshseq?)")
        return ModelConfig(**d)


# --------------------------------------------------------------------------------------------
# 1-ring mean operators
#
# Inside the network, frames are vertex-major: ``(V, B, C)``. The ring mean is then a sparse
# matrix times the ``(V, B*C)`` view and the channel maps are one ``(V*B, C) @ (C, C)`` matmul,
# with no transposes; only the FC layers need ``(B, V*C)`` (one copy in, one out per step).


class _SparseMean(torch.autograd.Function):
    """``A @ x`` for a constant sparse ``A`` with a precomputed transpose for the backward pass."""

    @staticmethod
    def forward(ctx, x, A, At):
        ctx.At = At
        return A @ x

    @staticmethod
    def backward(ctx, g):
        return ctx.At @ g.contiguous(), None, None


class NeighborMean(nn.Module):
    """The 1-ring mean ``(1/d_i) sum_{j in N(i)} x_j`` of vertex-major tensors ``(V, ...)``.

    ``impl="sparse"``: a row-normalised sparse ``(V, V)`` CSR matrix times the ``(V, N)`` view;
    ``impl="gather"``: a padded ``(V, D)`` index table (D the largest degree) and weights
    ``mask / d`` (work ``V D N``). Isolated vertices (degree 0) get 0.
    """

    def __init__(self, topology: Topology, impl: str = "sparse"):
        super().__init__()
        if impl not in CONV_IMPLS:
            raise MeshseqError(f"--conv {impl!r}: expected one of {', '.join(CONV_IMPLS)}")
        self.impl = impl
        self.n_vertices = topology.n_vertices
        deg = np.maximum(topology.degrees, 1).astype(np.float64)
        if impl == "gather":
            index, mask = topology.padded_neighbors()
            weight = mask / deg[:, None]
            self.register_buffer("index", torch.from_numpy(index.reshape(-1)).long(), persistent=False)
            self.register_buffer("weight", torch.from_numpy(weight).float(), persistent=False)
            self.width = index.shape[1]
        else:
            adj = topology.adjacency.tocoo()
            vals = 1.0 / deg[adj.row]
            ij = torch.from_numpy(np.stack([adj.row, adj.col])).long()
            n = self.n_vertices
            v = torch.from_numpy(vals).float()
            with warnings.catch_warnings():
                warnings.filterwarnings("ignore", message=".*[Ss]parse CSR tensor support is in beta.*")
                A = torch.sparse_coo_tensor(ij, v, (n, n), check_invariants=True).coalesce()
                At = torch.sparse_coo_tensor(ij.flip(0), v, (n, n), check_invariants=True).coalesce()
                self.register_buffer("A", A.to_sparse_csr(), persistent=False)
                self.register_buffer("At", At.to_sparse_csr(), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` ``(V, ...)`` -> ``(V, ...)``."""
        V = x.shape[0]
        xv = x.reshape(V, -1)
        if self.impl == "gather":
            g = xv.index_select(0, self.index).view(V, self.width, -1)
            y = torch.einsum("vdn,vd->vn", g, self.weight)
        else:
            y = _SparseMean.apply(xv, self.A, self.At)
        return y.view(x.shape)


class MeshConv(nn.Module):
    """Paper Eq. 2 on vertex-major ``(V, ..., C_in)`` -> ``(V, ..., C_out)``: ``x W1 + mean_ring(x) W2 + b``.

    ``forward(x, transpose=True, bias=b)`` applies the layer's weights transposed with another
    bias (the tied decoder), ``(V, ..., C_out)`` -> ``(V, ..., C_in)``.
    """

    def __init__(self, c_in: int, c_out: int, ring: NeighborMean):
        super().__init__()
        self.ring = ring
        bound = 1.0 / math.sqrt(2 * c_in)
        self.weight = nn.Parameter(torch.empty(2 * c_in, c_out).uniform_(-bound, bound))  # [W1; W2]
        self.bias = nn.Parameter(torch.zeros(c_out))
        self.c_in, self.c_out = c_in, c_out

    def forward(self, x: torch.Tensor, transpose: bool = False, bias: torch.Tensor | None = None):
        if transpose:
            w1, w2 = self.weight[: self.c_in].t(), self.weight[self.c_in :].t()
        else:
            w1, w2 = self.weight[: self.c_in], self.weight[self.c_in :]
        b = self.bias if bias is None else bias
        rows = x.reshape(-1, x.shape[-1])
        # mean_ring(x) W2 == mean_ring(x W2): apply the (linear) ring mean after the channel map.
        y = torch.addmm(b, rows, w1).view(*x.shape[:-1], -1)
        return y + self.ring((rows @ w2).view(*x.shape[:-1], -1))


# --------------------------------------------------------------------------------------------
# the big FC layer, with its weight gradient summed over time in one matmul


class _GradBank:
    """Pairs ``(left (B, L), right (B, N))`` whose products ``left^T right`` sum to a weight gradient."""

    def __init__(self):
        self.left: list[torch.Tensor] = []
        self.right: list[torch.Tensor] = []

    def gradient(self) -> torch.Tensor | None:
        if not self.left:
            return None
        g = torch.cat(self.left).t() @ torch.cat(self.right)
        self.left.clear()
        self.right.clear()
        return g


class _WeightGate(torch.autograd.Function):
    """Identity on the FC weight for one roll-out; its backward hands over the collected gradient.

    The steps' ``_DeferredLinear`` nodes give it no gradient; they store their (input, output
    gradient) pairs in the bank instead, and this node (which autograd runs after all of them)
    forms ``sum_t a_t^T b_t`` as ONE matmul over all time steps, instead of one memory-bound
    ``(L, V*C)`` product and accumulation per step and layer.
    """

    @staticmethod
    def forward(ctx, weight, bank):
        ctx.set_materialize_grads(False)
        ctx.bank = bank
        return weight.view_as(weight)

    @staticmethod
    def backward(ctx, grad):
        g = ctx.bank.gradient()
        if grad is not None:
            g = grad if g is None else g + grad
        return g, None


class _DeferredLinear(torch.autograd.Function):
    """``x W^T + b`` (``transpose=False``) or ``x W + b`` (``transpose=True``), W ``(L, N)``;
    the weight gradient goes to the bank (see ``_WeightGate``)."""

    @staticmethod
    def forward(ctx, x, weight, bias, bank, transpose):
        ctx.save_for_backward(x, weight)
        ctx.bank, ctx.transpose = bank, transpose
        return torch.addmm(bias, x, weight if transpose else weight.t())

    @staticmethod
    def backward(ctx, g):
        x, weight = ctx.saved_tensors
        if ctx.transpose:  # y = x W: dW = x^T g
            gx = g @ weight.t()
            ctx.bank.left.append(x)
            ctx.bank.right.append(g)
        else:  # y = x W^T: dW = g^T x
            gx = g @ weight
            ctx.bank.left.append(g)
            ctx.bank.right.append(x)
        return gx, None, g.sum(0), None, None


class _FC:
    """How a roll-out applies the big FC weight: plainly, or through the gate and bank (training)."""

    def __init__(self, weight: torch.Tensor, deferred: bool):
        self.bank = _GradBank() if deferred else None
        self.weight = _WeightGate.apply(weight, self.bank) if deferred else weight

    def encode(self, x, bias):  # (B, N) -> (B, L)
        if self.bank is None:
            return F.linear(x, self.weight, bias)
        return _DeferredLinear.apply(x, self.weight, bias, self.bank, False)

    def decode(self, h, bias):  # (B, L) -> (B, N)
        if self.bank is None:
            return torch.addmm(bias, h, self.weight)
        return _DeferredLinear.apply(h, self.weight, bias, self.bank, True)


# --------------------------------------------------------------------------------------------
# the generator


class BDLSTM(nn.Module):
    """Encoder (Conv + FC + VAE head), LSTM(s), tied decoder; see the module docstring.

    Public methods take frames ``(B, V, C)``; the ``_vm`` methods work on vertex-major
    ``(V, B, C)`` frames, the layout of the roll-out. Parameters are created in a fixed order, so
    a seed gives the same initial weights on every machine and every rank.
    """

    def __init__(self, config: ModelConfig, topology: Topology):
        super().__init__()
        if topology.n_vertices != config.n_vertices:
            raise MeshseqError(
                f"mesh has {topology.n_vertices} vertices but the model expects {config.n_vertices}"
            )
        self.config = config
        C, L, V = config.channels, config.latent, config.n_vertices
        self.ring = NeighborMean(topology, config.conv_impl)
        self.convs = nn.ModuleList(MeshConv(C, C, self.ring) for _ in range(config.conv_layers))
        self.fc = nn.Linear(V * C, L)
        self.fc_mu = nn.Linear(L, L)
        self.fc_logvar = nn.Linear(L, L)
        # decoder's own biases: FC^T bias (V*C), then one per conv layer (decoder order)
        self.dec_fc_bias = nn.Parameter(torch.zeros(V * C))
        self.dec_conv_bias = nn.ParameterList(nn.Parameter(torch.zeros(C)) for _ in range(config.conv_layers))
        self.lstm = nn.LSTM(L, L, config.lstm_layers)
        self.lstm_backward = nn.LSTM(L, L, config.lstm_layers) if config.variant == "std-bd" else None

    def _fc_ops(self, deferred: bool = False) -> _FC:
        return _FC(self.fc.weight, deferred and torch.is_grad_enabled() and self.fc.weight.requires_grad)

    # -- the pieces (vertex-major) --------------------------------------------------------------

    def _encode_vm(self, x: torch.Tensor, fc: _FC) -> tuple[torch.Tensor, torch.Tensor]:
        """``(V, B, C)`` -> ``(mu, logvar)`` ``(B, L)``."""
        for conv in self.convs:
            x = torch.tanh(conv(x))
        flat = x.transpose(0, 1).reshape(x.shape[1], -1)  # (B, V*C), vertex-major flattening
        e = fc.encode(flat, self.fc.bias)
        return self.fc_mu(e), self.fc_logvar(e)

    def _decode_vm(self, h: torch.Tensor, fc: _FC) -> torch.Tensor:
        """``(B, L)`` -> ``dX`` ``(V, B, C)``."""
        B = h.shape[0]
        y = fc.decode(h, self.dec_fc_bias).view(B, self.config.n_vertices, -1).transpose(0, 1).contiguous()
        K = len(self.convs)
        for k in range(K):
            y = self.convs[K - 1 - k](y, transpose=True, bias=self.dec_conv_bias[k])
            if k < K - 1:
                y = torch.tanh(y)
        return y

    def _step_vm(self, state, x, fc: _FC, sample: bool, n_forward):
        mu, logvar = self._encode_vm(x, fc)
        z = mu + torch.exp(0.5 * logvar) * torch.randn_like(mu) if sample else mu
        h, state = self._lstm(z, state, n_forward)
        return state, x + self._decode_vm(h, fc), mu, logvar

    # -- public, batch-major ----------------------------------------------------------------------

    def encode(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Frames ``(B, V, C)`` -> ``(mu, logvar)``, each ``(B, L)``."""
        return self._encode_vm(x.transpose(0, 1), self._fc_ops())

    def decode(self, h: torch.Tensor) -> torch.Tensor:
        """LSTM outputs ``(B, L)`` -> frame changes ``dX`` ``(B, V, C)`` (tied weights)."""
        return self._decode_vm(h, self._fc_ops()).transpose(0, 1)

    def initial_state(self, n_forward: int, n_backward: int = 0, device=None, dtype=torch.float32):
        """``(h, c)``, each ``(K, n_forward + n_backward, L)``: +init for forward rows, -init after."""
        K, L, v = self.config.lstm_layers, self.config.latent, self.config.init_state
        sign = torch.cat([torch.ones(n_forward), -torch.ones(n_backward)]).to(device=device, dtype=dtype)
        s = (v * sign).view(1, -1, 1).expand(K, -1, L).contiguous()
        return s, s.clone()

    def _lstm(self, z: torch.Tensor, state, n_forward: int | None):
        """One LSTM step for ``z`` ``(B, L)``; rows ``n_forward:`` use the backward LSTM (std-bd)."""
        h, c = state
        if self.lstm_backward is None or n_forward is None or n_forward >= z.shape[0]:
            out, (h2, c2) = self.lstm(z.unsqueeze(0), (h, c))
            return out[0], (h2, c2)
        if n_forward <= 0:
            out, (h2, c2) = self.lstm_backward(z.unsqueeze(0), (h, c))
            return out[0], (h2, c2)
        f = slice(0, n_forward)
        b = slice(n_forward, None)
        of, (hf, cf) = self.lstm(z[f].unsqueeze(0), (h[:, f].contiguous(), c[:, f].contiguous()))
        ob, (hb, cb) = self.lstm_backward(z[b].unsqueeze(0), (h[:, b].contiguous(), c[:, b].contiguous()))
        return torch.cat([of[0], ob[0]]), (torch.cat([hf, hb], 1), torch.cat([cf, cb], 1))

    def step(self, state, x: torch.Tensor, sample: bool = False, n_forward: int | None = None):
        """G(s, X) -> (s', X + dX).

        Args:
            state: ``(h, c)``, each ``(K, B, L)``.
            x: current frames ``(B, V, C)`` (scaled features).
            sample: draw ``z = mu + sigma eps`` (training) instead of ``z = mu``.
            n_forward: rows ``[:n_forward]`` are forward chains, the rest backward chains (only
                matters for ``std-bd``; None = all rows forward).
        Returns:
            ``(state', x_next (B, V, C), mu (B, L), logvar (B, L))``.
        """
        state, nxt, mu, logvar = self._step_vm(state, x.transpose(0, 1), self._fc_ops(), sample, n_forward)
        return state, nxt.transpose(0, 1), mu, logvar

    def rollout(self, first: torch.Tensor, steps: int, state, sample: bool = False, n_forward=None):
        """Free-running roll-out from ``first`` ``(B, V, C)``.

        Returns ``(frames (B, steps + 1, V, C)`` with ``frames[:, 0] = first``, ``mu``, ``logvar``
        ``(steps, B, L)``, final state)``. The time loop is the only Python loop.
        """
        fc = self._fc_ops(deferred=True)
        x = first.transpose(0, 1).contiguous()  # (V, B, C)
        frames, mus, logvars = [x], [], []
        for _ in range(steps):
            state, x, mu, logvar = self._step_vm(state, x, fc, sample, n_forward)
            frames.append(x)
            mus.append(mu)
            logvars.append(logvar)
        out = torch.stack(frames).permute(2, 0, 1, 3)  # (n, V, B, C) -> (B, n, V, C)
        if steps:
            return out, torch.stack(mus), torch.stack(logvars), state
        empty = first.new_zeros(0, first.shape[0], self.config.latent)
        return out, empty, empty, state

    def forward(self, windows: torch.Tensor, sample: bool = True) -> dict:
        """Both chains over ground-truth windows ``(B, n, V, C)`` in one batched pass.

        Returns a dict with ``forward`` ``(B, n, V, C)`` (S^f_1..S^f_n, S^f_1 = X_1), ``backward``
        ``(B, n, V, C)`` in the backward chain's own order (S^b_1 = X_n, ..., S^b_n ~ X_1; None for
        ``uni``), ``mu`` and ``logvar`` ``(n - 1, B or 2B, L)``.
        """
        B, n = windows.shape[:2]
        if self.config.variant == "uni":
            state = self.initial_state(B, 0, windows.device, windows.dtype)
            frames, mu, logvar, _ = self.rollout(windows[:, 0], n - 1, state, sample=sample)
            return {"forward": frames, "backward": None, "mu": mu, "logvar": logvar}
        first = torch.cat([windows[:, 0], windows[:, -1]])  # forward chains, then backward chains
        state = self.initial_state(B, B, windows.device, windows.dtype)
        frames, mu, logvar, _ = self.rollout(first, n - 1, state, sample=sample, n_forward=B)
        return {"forward": frames[:B], "backward": frames[B:], "mu": mu, "logvar": logvar}

    def weight_parameters(self) -> list[torch.Tensor]:
        """Parameters counted by L_2 (weight matrices; biases excluded), each once."""
        return [p for name, p in self.named_parameters() if p.dim() >= 2]


def count_step_flops(config: ModelConfig, topology: Topology, batch: int) -> dict:
    """Multiply-add FLOPs (2 per MAC) of one forward ``step`` for ``batch`` rows, by part.

    Counts the dense arithmetic: conv channel maps (2 matmuls of C x C per vertex and layer, in
    encoder and decoder), ring means (one add per neighbour entry and channel, plus the scale),
    the big FC (encoder) and its transpose (decoder), the VAE head and the LSTM gates. Elementwise
    activations are left out (a few per entry; small next to the rest).
    """
    V, C, L, K, NL = config.n_vertices, config.channels, config.latent, config.conv_layers, config.lstm_layers
    nnz = int(topology.degrees.sum())
    conv = K * 2 * (2 * 2 * V * C * C + 2 * nnz * C)  # enc + dec, each: 2 CxC matmuls + ring mean
    fc = 2 * (2 * V * C * L)  # encoder FC + tied decoder FC
    head = 2 * 2 * L * L
    lstm = NL * 2 * 4 * L * (2 * L)
    per_row = {"conv": conv, "fc": fc, "head": head, "lstm": lstm}
    return {k: v * batch for k, v in per_row.items()}

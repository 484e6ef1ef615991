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
``MeshConv.forward`` is the readable reference; ``rollout`` runs the encoder's and the decoder's
conv layers as one ``meshseq.kernels.MeshConvStack`` each (the fast path: fused layers with a
hand-written backward, a C++ kernel on CPU; see that module), equal to the reference to float32
rounding.

Layout: inside, frames are vertex-major ``(V, C, B)`` (vertex, channel, window): a vertex's
channels of all windows are one contiguous block (what the ring mean gathers), and the flattened
``(V*C, B)`` view is the big FC's input in the order of its weight's columns.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import torch
from torch import nn

from meshseq.errors import MeshseqError
from meshseq.kernels import (LSTMStep, MeshConvStack, fc_product, fc_product_and_row_sums, fc_transposed_product,
                             fc_weight_gradient, fc_weight_gradient_supported, lstm_step_supported,
                             lstm_transposed, stack_frames)
from meshseq.mesh import Topology
from meshseq.model_config import (CONV_IMPLS, MODEL_OPTIONS, VARIANTS, ModelConfig,  # noqa: F401 (re-exported)
                                  is_finite_number)
from meshseq.numpy_net import ring_matrix

# --------------------------------------------------------------------------------------------
# 1-ring mean operators
#
# Inside the network, frames are channel-major: ``(C, V, B)``. Then the channel maps are one
# ``(C, C) @ (C, V*B)`` matmul each (the fast shape for a 9 x 9 map), the ring mean is one
# block-diagonal sparse matrix ``I_C (x) A`` times the ``(C*V, B)`` view, and the FC layers are
# ``(L, C*V) @ (C*V, B)`` matmuls: no transposes or copies inside a step.


def _csr(matrix) -> torch.Tensor:
    """A float32 torch CSR tensor of a scipy sparse matrix (duplicates summed, columns sorted), built
    from the CSR arrays directly (through COO, ``coalesce`` took 0.2 s for crane's ring matrix)."""
    m = matrix.tocsr(copy=True)
    m.sum_duplicates()  # (also sorts the column indices)
    # the invariant checks asked for explicitly (a context, not the keyword: torch 2.11 warns that
    # they are "implicitly disabled" when only the keyword asks for them)
    with warnings.catch_warnings(), torch.sparse.check_sparse_tensor_invariants():
        warnings.filterwarnings("ignore", message=".*[Ss]parse CSR tensor support is in beta.*")
        return torch.sparse_csr_tensor(torch.from_numpy(m.indptr).long(), torch.from_numpy(m.indices).long(),
                                       torch.from_numpy(m.data).float(), m.shape)


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

    Keeps the row-normalised adjacency ``A`` ``(V, V)`` and its transpose as CSR tensors (the
    fused kernels read their index lists). ``impl`` chooses the reference's ``forward``:
    ``"sparse"``, ``A @ x`` on the ``(V, rest)`` view; ``"gather"``, a padded ``(V, D)`` index table
    (D the largest degree) and weights ``mask / d``. Isolated vertices (degree 0) get 0.
    """

    def __init__(self, topology: Topology, impl: str = "sparse"):
        super().__init__()
        if impl not in CONV_IMPLS:
            raise MeshseqError(f"--conv {impl!r}: expected one of {', '.join(CONV_IMPLS)}")
        self.impl = impl
        self.n_vertices = topology.n_vertices
        deg = np.maximum(topology.degrees, 1).astype(np.float64)
        A = ring_matrix(topology, np.float64)
        self.register_buffer("A", _csr(A), persistent=False)
        self.register_buffer("At", _csr(A.T.tocsr()), persistent=False)
        if impl == "gather":
            index, mask = topology.padded_neighbors()
            self.register_buffer("index", torch.from_numpy(index.reshape(-1)).long(), persistent=False)
            self.register_buffer("weight", torch.from_numpy(mask / deg[:, None]).float(), persistent=False)
            self.width = index.shape[1]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` ``(V, ...)`` -> ``(V, ...)``."""
        V = x.shape[0]
        cols = x.reshape(V, -1)
        if self.impl == "gather":
            g = cols.index_select(0, self.index).view(V, self.width, -1)
            return torch.einsum("vdn,vd->vn", g, self.weight).view(x.shape)
        return _SparseMean.apply(cols, self.A, self.At).view(x.shape)


class MeshConv(nn.Module):
    """Paper Eq. 2 on vertex-major ``(V, C_in, ...)`` -> ``(V, C_out, ...)``.

    Per vertex ``y_i = W1^T x_i + W2^T mean_ring(x)_i + b`` (``weight = [W1; W2]``,
    ``(2 C_in, C_out)``). ``forward(x, transpose=True, bias=b)`` applies the layer's weights
    transposed with another bias (the tied decoder), ``(C_out, V, ...)`` -> ``(C_in, V, ...)``.
    """

    def __init__(self, c_in: int, c_out: int, ring: NeighborMean):
        super().__init__()
        self.ring = ring
        bound = 1.0 / math.sqrt(2 * c_in)
        self.weight = nn.Parameter(torch.empty(2 * c_in, c_out).uniform_(-bound, bound))  # [W1; W2]
        self.bias = nn.Parameter(torch.zeros(c_out))
        self.c_in, self.c_out = c_in, c_out

    def forward(self, x: torch.Tensor, transpose: bool = False, bias: torch.Tensor | None = None):
        w1, w2 = self.weight[: self.c_in], self.weight[self.c_in :]  # (C_in, C_out) each
        if not transpose:  # y = W^T x per vertex
            w1, w2 = w1.t(), w2.t()
        b = self.bias if bias is None else bias
        cols = x.reshape(x.shape[0], x.shape[1], -1)  # (V, C_in, N)
        y = torch.einsum("oc,vcn->von", w1, cols) + torch.einsum("oc,vcn->von", w2, self.ring(cols))
        return (y + b[:, None]).view((x.shape[0], w1.shape[0]) + tuple(x.shape[2:]))


# --------------------------------------------------------------------------------------------
# the big FC layer, with its weight gradient summed over time in one matmul
#
# The parameter ``fc.weight`` is ``(L, V*C)`` with columns in vertex-major order (vertex v,
# channel c at v*C + c), the order of the roll-out's flattened ``(V*C, B)`` frames; likewise
# ``dec_fc_bias`` ``(V*C,)``.


class _Scratch:
    """One reusable flat buffer per dtype and device (the gradient bank's ``R``, 300 MB on the horse).

    A fresh tensor of that size costs a page fault per 4 KiB page when first written: the bank's
    concatenation took 106 ms into a new tensor against 26 ms into a reused one (horse, 2 threads).
    Not part of the model's state; grows to the largest size asked for.
    """

    def __init__(self):
        self.buffers: dict[tuple, torch.Tensor] = {}

    def take(self, shape: tuple[int, ...], like: torch.Tensor) -> torch.Tensor:
        """A contiguous tensor of ``shape`` with ``like``'s dtype and device, contents undefined;
        valid until the next ``take`` of the same dtype and device."""
        key = (like.dtype, like.device)
        numel = math.prod(shape)
        buf = self.buffers.get(key)
        if buf is None or buf.numel() < numel:
            self.buffers.pop(key, None)  # free the old one first
            buf = self.buffers[key] = torch.empty(numel, dtype=like.dtype, device=like.device)
        return buf[:numel].view(shape)


class _GradBank:
    """Pairs ``(left (B, L), right (N, B))`` whose products ``(right left)^T`` sum to a weight gradient.

    ``encoder_scale`` multiplies the encoder's pairs (``BDLSTM.encoder_grad_scale``).

    ``right`` is kept as the ``(N, B)`` frame it is (no transposing copy per step). On CPU in
    float32 the sum is ``kernels.fc_weight_gradient`` (reads the pairs where they lie); otherwise
    ``(R L)^T`` with ``R = [right_1 ... right_T]`` ``(N, T B)`` (one 64-byte-row copy, into
    ``scratch``'s reused buffer) by blocks of ``ROWS`` rows."""

    ROWS = 1024  # rows of R per block of the weight-gradient product (its 512 KB product fits in L2)

    def __init__(self, encoder_scale: float, scratch: _Scratch):
        self.left: list[torch.Tensor] = []
        self.right: list[torch.Tensor] = []
        self.encoder_scale = encoder_scale  # ``BDLSTM.encoder_grad_scale``: on the encoder's pairs
        self.scratch = scratch

    def gradient(self) -> torch.Tensor | None:
        if not self.left:
            return None
        left = torch.cat(self.left)  # (T B, L)
        if fc_weight_gradient_supported(left, self.right):  # CPU float32: csrc/fc.cpp, no copies
            g = fc_weight_gradient(left, self.right)
        else:
            g = self._blocked_product(left)
        self.left.clear()
        self.right.clear()
        return g

    def _blocked_product(self, left: torch.Tensor) -> torch.Tensor:
        """``(R left)^T`` by torch (other devices and dtypes): ``R`` concatenated, then blocks of rows."""
        cols = sum(r.shape[1] for r in self.right)
        N = self.right[0].shape[0]
        R = torch.cat(self.right, 1, out=self.scratch.take((N, cols), self.right[0]))
        # (R left)^T in the weight's own layout (L, N), a block of R's rows at a time: each block's
        # product is transposed while in cache; one whole product transposed after (autograd
        # keeps a gradient in its parameter's layout) cost a 39 MB strided copy (150 -> 132 ms);
        # blocks of 1024 rows (512 KB, in L2) instead of 4096: 134 -> 124 ms (10th percentile), same bits
        g = torch.empty(left.shape[1], N, dtype=torch.float32, device=R.device)
        for a in range(0, N, self.ROWS):
            b = min(N, a + self.ROWS)
            g[:, a:b].copy_((R[a:b] @ left).t())
        return g


def lstm_step(lstm: nn.LSTM, z: torch.Tensor, h: torch.Tensor, c: torch.Tensor, transposed=None):
    """One time step of a stacked ``nn.LSTM`` (unidirectional, no projection or dropout):
    ``z`` ``(B, L_in)``, ``h``, ``c`` ``(K, B, L)`` -> ``(out (B, L), (h', c'))``, the module's
    arithmetic, as ``torch.lstm_cell`` layer by layer. (The module's one-step call went through
    oneDNN's sequence kernel: 59 against 40 ms for the 31 steps of a roll-out, forward and
    backward, 16 chains of 128, 2 threads; the results agree to float32 rounding.)

    ``transposed``: ``kernels.lstm_transposed(lstm)`` (the roll-out's fast path makes it once):
    then, where ``kernels.lstm_step_supported``, all layers run as one ``kernels.LSTMStep``
    (``csrc/lstm.cpp``; 58.6 -> 41.8 ms for a roll-out's 31 steps forward + backward, isolated).
    """
    if transposed is not None and lstm_step_supported(lstm, z):
        params = [getattr(lstm, f"{n}_l{k}") for k in range(lstm.num_layers)
                  for n in ("weight_ih", "weight_hh", "bias_ih", "bias_hh")]
        h_out, c_out = LSTMStep.apply(z, h, c, transposed, *params)
        return h_out[-1], (h_out, c_out)
    hs, cs = [], []
    x = z
    for k in range(lstm.num_layers):
        x, ck = torch.lstm_cell(x, (h[k], c[k]), getattr(lstm, f"weight_ih_l{k}"), getattr(lstm, f"weight_hh_l{k}"),
                                getattr(lstm, f"bias_ih_l{k}"), getattr(lstm, f"bias_hh_l{k}"))
        hs.append(x)
        cs.append(ck)
    return x, (torch.stack(hs), torch.stack(cs))


class _WeightGate(torch.autograd.Function):
    """The FC weight for one roll-out; its backward hands over the collected gradient.

    The steps' ``_Encode``/``_Decode`` nodes give it no gradient; they store their (input,
    output gradient) pairs in the bank instead, and this node (which autograd runs after all of
    them) forms ``sum_t a_t^T b_t`` as ONE matmul over all time steps, instead of one
    memory-bound ``(L, V*C)`` product and accumulation per step and layer.
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


class _ScaleGradient(torch.autograd.Function):
    """The identity whose backward multiplies the gradient by ``scale`` (the encoder's read of the
    tied FC weight outside the banked roll-out: warm-up steps, the plain reference)."""

    @staticmethod
    def forward(ctx, weight, scale):
        ctx.scale = scale
        return weight.view_as(weight)

    @staticmethod
    def backward(ctx, grad):
        return ctx.scale * grad, None


class _Encode(torch.autograd.Function):
    """``e = x^T W^T + b``: x ``(N, B)`` (flattened frames), W ``(L, N)`` -> ``(B, L)``.

    ``weight`` may be a low-precision (bfloat16) copy: the products then run in that precision
    and the results come back in ``x``'s dtype (float32).
    """

    @staticmethod
    def forward(ctx, x, weight, bias, bank):
        ctx.save_for_backward(x, weight)
        ctx.bank = bank
        # (W x)^T: W (L, N) times x (N, B) (with torch: MKL's fast orientation, 4.3 ms against
        # 6.1 ms for x^T W^T, horse, 16 columns, 2 threads)
        return fc_product(weight, x, bias).t().to(x.dtype)

    @staticmethod
    def backward(ctx, g):  # g (B, L)
        x, weight = ctx.saved_tensors
        scaled = g if ctx.bank.encoder_scale == 1.0 else ctx.bank.encoder_scale * g
        ctx.bank.left.append(scaled.to(weight.dtype))
        ctx.bank.right.append(x.to(weight.dtype))  # dW = g^T x^T = (x g)^T (times the encoder's scale)
        # (N, B) contiguous, the layout the conv layer's backward reads (no transposing copy)
        return fc_transposed_product(weight, g.t()).to(g.dtype), None, g.sum(0), None


class _Decode(torch.autograd.Function):
    """``y = W^T h^T + b``: h ``(B, L)``, W ``(L, N)`` -> ``(N, B)`` (flattened frames)."""

    @staticmethod
    def forward(ctx, h, weight, bias, bank):
        ctx.save_for_backward(h, weight)
        ctx.bank = bank
        if weight.dtype == bias.dtype:
            return fc_transposed_product(weight, h.t(), bias)
        return fc_transposed_product(weight, h.t()).to(bias.dtype).add_(bias[:, None])

    @staticmethod
    def backward(ctx, g):  # g (N, B)
        h, weight = ctx.saved_tensors
        ctx.bank.left.append(h.to(weight.dtype))
        ctx.bank.right.append(g.to(weight.dtype))  # dW = h^T g^T = (g h)^T
        gh, g_bias = fc_product_and_row_sums(weight, g)  # the bias gradient: g's row sums
        return gh.t().to(g.dtype), None, g_bias, None


def _normalizing_layer(model: "BDLSTM", w_self: torch.Tensor, w_ring: torch.Tensor, bias: torch.Tensor):
    """The encoder's first layer with the input normalisation folded in: ``(w_self', w_ring', bias')``
    that map the raw frame ``x`` as ``(w_self, w_ring, bias)`` map ``x_n = (x - offset) / spread``.

    The ring mean acts on vertices and the normalisation per vertex and channel, so with
    ``W' = W diag(1 / spread)``: ``W_s x_n + W_r (A x_n) + b = W_s' x + W_r' (A x) + b'_v``,
    ``b'_v = b - W_s' offset_v - W_r' (A offset)_v`` (a bias per vertex, ``(V, C_out)``). The roll-out
    then never makes (nor saves for its backward) a normalised copy of each frame: that copy and
    its backward pass cost the default recipe 56 +- 10 ms an iteration on the horse. Gradients
    flow to ``w_self``, ``w_ring``, ``bias`` through these few small operations."""
    with torch.autocast(model.input_offset.device.type, enabled=False):  # float32 under --precision bf16 too
        with torch.no_grad():
            inv = 1.0 / model.input_spread.view(-1)  # (C,)
            offset = model.input_offset[:, :, 0].t().contiguous()  # (V, C)
            ring_offset = model.ring(offset)  # (V, C)
        w_self, w_ring = w_self * inv, w_ring * inv  # the input channels (columns) scaled
        return w_self, w_ring, (bias - offset @ w_self.t() - ring_offset @ w_ring.t()).contiguous()


class _FC:
    """The big FC weight (and decoder bias) of one roll-out; with ``deferred`` (training) its
    weight gradient is formed once, after all steps.

    ``fused``: the roll-out's conv layers run as ``kernels.MeshConvStack`` (the fast path), with
    the channel maps of every encoder and decoder layer sliced from the parameters once per
    roll-out; otherwise ``MeshConv.forward`` (the reference).
    """

    def __init__(self, model: "BDLSTM", deferred: bool, fused: bool = False):
        self.fused = fused
        if self.fused:
            # (w_self, w_ring, bias) per layer, (C_out, C_in): encoder W^T, decoder W (tied)
            # contiguous once per roll-out (the C++ layers would copy a transposed view at every call)
            self.enc = [(c.weight[: c.c_in].t().contiguous(), c.weight[c.c_in :].t().contiguous(), c.bias)
                        for c in model.convs]
            if model.config.input_norm:
                self.enc[0] = _normalizing_layer(model, *self.enc[0])
            K = len(model.convs)
            self.dec = [
                (model.convs[K - 1 - k].weight[: model.convs[K - 1 - k].c_in],
                 model.convs[K - 1 - k].weight[model.convs[K - 1 - k].c_in :], model.dec_conv_bias[k])
                for k in range(K)
            ]
            self.ring = model.ring
        self._lstm_transposed: dict[int, tuple] = {}  # id(nn.LSTM) -> kernels.lstm_transposed, once per roll-out
        scale = float(model.encoder_grad_scale)
        self.bank = _GradBank(scale, model._scratch) if deferred else None
        self.enc_weight = None  # the weight the encoder reads, when its gradient is scaled (not deferred)
        if deferred:
            self.weight = _WeightGate.apply(model.fc.weight, self.bank)
            dev = model.fc.weight.device.type
            if torch.is_autocast_enabled(dev) and torch.get_autocast_dtype(dev) == torch.bfloat16:
                # --precision bf16: one bfloat16 copy of the big weight per roll-out; the per-step
                # products read half the bytes (and run at the bf16 rate); master weight stays float32
                self.weight = self.weight.to(torch.bfloat16)
        else:
            self.weight = model.fc.weight
            if scale != 1.0 and self.weight.requires_grad and torch.is_grad_enabled():
                self.enc_weight = _ScaleGradient.apply(self.weight, scale)
        self.bias = model.fc.bias
        self.dec_bias = model.dec_fc_bias

    def lstm_weights(self, lstm: nn.LSTM):
        """``kernels.lstm_transposed(lstm)`` for the fast path's LSTM steps (made on first use); None
        off the fast path (the steps then run ``torch.lstm_cell``)."""
        if not self.fused:
            return None
        if id(lstm) not in self._lstm_transposed:
            self._lstm_transposed[id(lstm)] = lstm_transposed(lstm)
        return self._lstm_transposed[id(lstm)]

    def encode(self, x):  # (V*C, B) -> (B, L)
        if self.bank is None:
            w = self.weight if self.enc_weight is None else self.enc_weight
            return torch.addmm(self.bias[:, None], w, x).t()
        return _Encode.apply(x, self.weight, self.bias, self.bank)

    def decode(self, h):  # (B, L) -> (V*C, B)
        if self.bank is None:
            return torch.addmm(self.dec_bias[:, None], self.weight.t(), h.t())
        return _Decode.apply(h, self.weight, self.dec_bias, self.bank)


class RolloutOutput(dict):
    """``BDLSTM.forward``'s result: a dict whose stacked entries are made when first read.

    ``frames`` (``n`` vertex-major ``(V, C, R)`` tensors: the ``R = B`` forward chains, then, for
    the bidirectional variants, ``B`` backward chains), ``mu``, ``logvar`` are there from the start;
    ``chains`` ``(R, n, V, C)`` (``stack_frames``), ``forward`` and ``backward`` ``(B, n, V, C)``
    (one split of ``chains``; ``backward`` None without backward chains) are made on first access.
    The window losses read ``frames`` directly (``kernels.frame_errors_of_frames``), so a training
    step that needs nothing else never stacks them (155 MB on the horse, and a transposing copy
    of each frame's gradient).
    """

    def __init__(self, frames: list[torch.Tensor], n_forward: int | None, mu: torch.Tensor, logvar: torch.Tensor):
        super().__init__(frames=frames, mu=mu, logvar=logvar)
        self.n_forward = n_forward  # None: forward chains only
        if n_forward is None:
            self["backward"] = None

    def frames_at(self, indices: list[int]) -> torch.Tensor:
        """The chains' frames ``indices`` only, stacked: ``(R, len(indices), V, C)`` (``chains[:, indices]``
        without stacking the others; L_vertex reads 4 frames of 32)."""
        if "chains" in self:
            return self["chains"][:, indices]
        return stack_frames([self["frames"][i] for i in indices])

    def __missing__(self, key):
        if key == "chains":
            self["chains"] = stack_frames(self["frames"])
        elif key in ("forward", "backward"):
            if self.n_forward is None:
                self["forward"] = self["chains"]
            else:
                # one split (its backward joins the two gradients), not two slices (each of whose
                # backward would zero-fill a gradient of all 2B rows)
                self["forward"], self["backward"] = self["chains"].split(self.n_forward)
        else:
            raise KeyError(key)
        return self[key]


# --------------------------------------------------------------------------------------------
# the generator


class BDLSTM(nn.Module):
    """Encoder (Conv + FC + VAE head), LSTM(s), tied decoder; see the module docstring.

    Public methods take frames ``(B, V, C)``; the ``_vm`` methods work on vertex-major
    ``(V, C, B)`` frames, the layout of the roll-out. Parameters are created in a fixed order, so
    a seed gives the same initial weights on every machine and every rank.
    """

    #: roll-outs use the fused conv kernels (``meshseq.kernels``); False: the plain reference ops
    fast_path: bool = True
    #: the factor on the encoder's share of the tied FC weight's gradient (the decoder's share and
    #: every other gradient unchanged); set by training (``TrainConfig.fc_lr = "encoder"``), not stored
    encoder_grad_scale: float = 1.0

    def __init__(self, config: ModelConfig, topology: Topology):
        super().__init__()
        if topology.n_vertices != config.n_vertices:
            raise MeshseqError(
                f"mesh has {topology.n_vertices} vertices but the model expects {config.n_vertices}"
            )
        self.config = config
        self._scratch = _Scratch()  # reused work memory of training roll-outs (not state)
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
        scale = torch.ones(C) if config.step_scale is None else torch.tensor(config.step_scale)
        self.register_buffer("step_scale", scale.view(1, C, 1), persistent=False)  # from the config
        if config.input_norm:  # stored channel-major: (C, V, 1) and (C, 1, 1)
            self.register_buffer("input_offset", torch.zeros(C, V, 1))
            self.register_buffer("input_spread", torch.ones(C, 1, 1))

    def set_input_norm(self, frames: np.ndarray) -> None:
        """Fit the encoder's input normalisation on training frames ``(T, V, C)`` (scaled)."""
        if not self.config.input_norm:
            raise ValueError("set_input_norm: the model was built with input_norm=False")
        x = np.asarray(frames, dtype=np.float64)
        offset = x.mean(axis=0)  # (V, C)
        rms = np.sqrt(np.square(x - offset).mean(axis=(0, 1)))  # (C,)
        rms = np.maximum(rms, 1e-3 * max(float(rms.max()), 1e-12))
        with torch.no_grad():
            self.input_offset.copy_(torch.from_numpy(offset.T[:, :, None]).to(self.input_offset))
            self.input_spread.copy_(torch.from_numpy(rms[:, None, None]).to(self.input_spread))

    def _fc_ops(self, deferred: bool = False, fused: bool = False) -> _FC:
        return _FC(self, deferred and torch.is_grad_enabled() and self.fc.weight.requires_grad, fused)

    # -- the pieces (vertex-major) -------------------------------------------------------------

    def _encode_vm(self, x: torch.Tensor, fc: _FC) -> tuple[torch.Tensor, torch.Tensor]:
        """``(V, C, B)`` -> ``(mu, logvar)`` ``(B, L)``."""
        if self.config.input_norm and not fc.fused:  # (the fused layers fold it in: _normalizing_layer)
            x = (x - self.input_offset.permute(1, 0, 2)) / self.input_spread.view(1, -1, 1)
        if fc.fused:
            x = MeshConvStack.apply(x, None, fc.ring, (True,) * len(fc.enc), *(t for layer in fc.enc for t in layer))
        else:
            for conv in self.convs:
                x = torch.tanh(conv(x))
        e = fc.encode(x.reshape(-1, x.shape[-1]))
        logvar = self.fc_logvar(e)
        if self.config.logvar_max is not None:
            logvar = logvar.clamp(max=self.config.logvar_max)
        mu = self.fc_mu(e)
        if self.config.mu_max is not None:
            mu = self.config.mu_max * torch.tanh(mu / self.config.mu_max)
        return mu, logvar

    def _decode_vm(self, h: torch.Tensor, fc: _FC, residual: torch.Tensor | None = None) -> torch.Tensor:
        """``(B, L)`` -> ``dX`` ``(V, C, B)`` (``residual + dX`` when a residual is given)."""
        C, V = self.config.channels, self.config.n_vertices
        y = fc.decode(h).view(V, C, h.shape[0])
        K = len(self.convs)
        if fc.fused:
            acts = tuple(k < K - 1 for k in range(K))  # tanh after every layer but the last
            return MeshConvStack.apply(y, residual, fc.ring, acts, *(t for layer in fc.dec for t in layer))
        for k in range(K):
            y = self.convs[K - 1 - k](y, transpose=True, bias=self.dec_conv_bias[k])
            if k < K - 1:
                y = torch.tanh(y)
        return y if residual is None else residual + y

    def _step_vm(self, state, x, fc: _FC, sample: bool, n_forward, feedback_grad: bool = True):
        mu, logvar = self._encode_vm(x if feedback_grad else x.detach(), fc)
        z = mu + torch.exp(0.5 * logvar) * torch.randn_like(mu) if sample else mu
        h, state = self._lstm(z, state, n_forward, fc)
        if self.config.step_scale is not None:
            return state, x + self._decode_vm(h, fc) * self.step_scale, mu, logvar
        return state, self._decode_vm(h, fc, residual=x), mu, logvar

    # -- public, batch-major ----------------------------------------------------------------------

    def encode(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Frames ``(B, V, C)`` -> ``(mu, logvar)``, each ``(B, L)``."""
        return self._encode_vm(x.permute(1, 2, 0), self._fc_ops())

    def decode(self, h: torch.Tensor) -> torch.Tensor:
        """LSTM outputs ``(B, L)`` -> frame changes ``dX`` ``(B, V, C)`` (tied weights)."""
        return self._decode_vm(h, self._fc_ops()).permute(2, 0, 1)

    def initial_state(self, n_forward: int, n_backward: int = 0, device=None, dtype=torch.float32):
        """``(h, c)``, each ``(K, n_forward + n_backward, L)``: +init for forward rows, -init after."""
        K, L, v = self.config.lstm_layers, self.config.latent, self.config.init_state
        sign = torch.cat([torch.ones(n_forward), -torch.ones(n_backward)]).to(device=device, dtype=dtype)
        s = (v * sign).view(1, -1, 1).expand(K, -1, L).contiguous()
        return s, s.clone()

    def _lstm(self, z: torch.Tensor, state, n_forward: int | None, fc: _FC | None = None):
        """One LSTM step for ``z`` ``(B, L)``; rows ``n_forward:`` use the backward LSTM (std-bd).
        ``fc``: the roll-out's ``_FC`` (its fast path's LSTM weights), or None."""
        h, c = state

        def step(lstm, *args):
            return lstm_step(lstm, *args, transposed=None if fc is None else fc.lstm_weights(lstm))

        if self.lstm_backward is None or n_forward is None or n_forward >= z.shape[0]:
            return step(self.lstm, z, h, c)
        if n_forward <= 0:
            return step(self.lstm_backward, z, h, c)
        f = slice(0, n_forward)
        b = slice(n_forward, None)
        of, (hf, cf) = step(self.lstm, z[f], h[:, f], c[:, f])
        ob, (hb, cb) = step(self.lstm_backward, z[b], h[:, b], c[:, b])
        return torch.cat([of, ob]), (torch.cat([hf, hb], 1), torch.cat([cf, cb], 1))

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
        state, nxt, mu, logvar = self._step_vm(state, x.permute(1, 2, 0), self._fc_ops(), sample, n_forward)
        return state, nxt.permute(2, 0, 1), mu, logvar

    def rollout(self, first: torch.Tensor, steps: int, state, sample: bool = False, n_forward=None,
                feedback_grad: bool = True):
        """Free-running roll-out from ``first`` ``(B, V, C)``.

        ``feedback_grad=False``: each generated frame enters the next step's encoder as a constant
        (no gradient flows back through the encoder into the frames it was fed); the gradient
        still flows through the LSTM state and the residual ``X + dX``. Training only.

        Returns ``(frames (B, steps + 1, V, C)`` with ``frames[:, 0] = first``, ``mu``, ``logvar``
        ``(steps, B, L)``, final state)``. The time loop is the only Python loop.
        """
        frames, mu, logvar, state = self._rollout_vm(first, steps, state, sample, n_forward, feedback_grad)
        # (B, n, V, C), contiguous: one copy
        return stack_frames(frames), mu, logvar, state

    def _rollout_vm(self, first, steps, state, sample, n_forward, feedback_grad=True):
        """``rollout`` with the frames as it makes them: a list of ``steps + 1`` vertex-major
        ``(V, C, B)`` tensors (the first is ``first``'s)."""
        fc = self._fc_ops(deferred=True, fused=self.fast_path)
        x = first.permute(1, 2, 0).contiguous()  # (V, C, B)
        frames, mus, logvars = [x], [], []
        for _ in range(steps):
            state, x, mu, logvar = self._step_vm(state, x, fc, sample, n_forward, feedback_grad)
            frames.append(x)
            mus.append(mu)
            logvars.append(logvar)
        if steps:
            return frames, torch.stack(mus), torch.stack(logvars), state
        empty = first.new_zeros(0, first.shape[0], self.config.latent)
        return frames, empty, empty, state

    def forward(self, windows: torch.Tensor, sample: bool = True, given: int = 1,
                feedback_grad: bool = True) -> dict:
        """Both chains over ground-truth windows ``(B, n, V, C)`` in one batched pass.

        ``given`` (the paper: 1): each chain is fed its first ``given`` ground-truth frames
        (teacher-forced warm-up, as ``predict`` does with U given frames), then runs free. The
        outputs after a true frame are one-step predictions; every output counts in the loss.
        ``feedback_grad``: see ``rollout`` (False: the generated frames fed back are constants).

        Returns a ``RolloutOutput`` (a dict) with ``forward`` ``(B, n, V, C)`` (S^f_1..S^f_n,
        S^f_1 = X_1), ``backward`` ``(B, n, V, C)`` in the backward chain's own order (S^b_1 = X_n,
        ..., S^b_n ~ X_1; None for ``uni``), ``chains`` ``(B or 2B, n, V, C)`` (both, one tensor:
        forward, then backward), ``frames`` (the same as ``n`` vertex-major ``(V, C, B or 2B)``
        tensors, as the roll-out made them), ``mu`` and ``logvar`` ``(n - 1, B or 2B, L)``.
        """
        B, n = windows.shape[:2]
        given = max(1, min(int(given), n))
        uni = self.config.variant == "uni"
        n_forward = None if uni else B  # rows: forward chains, then backward chains
        state = self.initial_state(B, 0 if uni else B, windows.device, windows.dtype)

        def first(i):  # the chains' i-th true frame (B or 2B, V, C)
            return windows[:, i] if uni else torch.cat([windows[:, i], windows[:, n - 1 - i]])

        outs, mus, logvars = [], [], []
        for i in range(given - 1):  # teacher-forced warm-up: one step from each true frame
            frames, mu, logvar, state = self._rollout_vm(first(i), 1, state, sample, n_forward)
            outs += frames if i == 0 else frames[1:]  # the first keeps the true frame 0
            mus.append(mu)
            logvars.append(logvar)
        frames, mu, logvar, _ = self._rollout_vm(first(given - 1), n - given, state, sample, n_forward,
                                                 feedback_grad)
        if outs:  # after the warm-up: its frames, then the free chain without its (true) first frame
            frames = outs + frames[1:]
            mu, logvar = torch.cat(mus + [mu]), torch.cat(logvars + [logvar])
        return RolloutOutput(frames, None if uni else B, mu, logvar)

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

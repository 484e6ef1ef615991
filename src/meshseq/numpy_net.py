"""The generator's inference step in numpy and scipy: what ``predict`` and ``complete`` run on CPU
without importing torch (its import is most of a short command's time).

``NumpyNet`` (the interface of ``meshseq.torch_net.TorchNet``) computes what ``meshseq.model.BDLSTM.step`` computes with ``sample=False`` (see that
module's docstring for the step), from the same tensors (a checkpoint's ``model.*`` entries), to
float32 rounding (tests/test_numpy_net.py: 1e-5 on every variant, with and without input_norm):

- frames inside are vertex-major. With the compiled mesh convolution (``meshseq.native``: built
  with the system's C++ compiler on first use, no torch) and at least ``COMPILED_MIN_CHAINS``
  chains they are ``(V, C, Bp)``, the chains padded to a whole SIMD tile
  (``native.padded_chains``), and a conv layer is one pass of ``csrc/conv_forward.h`` (the
  training kernel's arithmetic). Otherwise ``(V, B, C)``: the ring
  mean is one scipy CSR product with the ``(V, B*C)`` view, a layer's channel maps are GEMMs of
  the ``(V*B, C)`` view;
- the big FC's weight columns are in the order ``v*C + c``: channel-major frames are its
  ``(V*C, Bp)`` columns as they lie, channel-last ones its ``(B, V*C)`` rows;
- an input normalisation is folded into the first conv layer (``folded_input_norm``);
- the LSTM layers are ``torch.lstm_cell``'s arithmetic, gates in torch's order ``i, f, g, o``.

Shapes: B rows (chains), V vertices, C channels, L latent, K LSTM layers. No sampling (the VAE
latent is its mean): sampling runs on the torch model.
"""

from __future__ import annotations

import numpy as np

from meshseq.errors import MeshseqError
from meshseq.model_config import ModelConfig

#: The fewest chains that run the compiled layers (``NumpyNet.channel_major``).
COMPILED_MIN_CHAINS = 5


def _sigmoid(x: np.ndarray) -> np.ndarray:
    """In place: ``1 / (1 + exp(-x))`` (``exp`` overflowing to infinity gives the limit 0)."""
    np.negative(x, out=x)
    with np.errstate(over="ignore"):
        np.exp(x, out=x)
    x += 1.0
    return np.reciprocal(x, out=x)


def ring_matrix(topology, dtype=np.float32):
    """The row-normalised 1-ring adjacency ``A`` ``(V, V)`` as a scipy CSR matrix (duplicates
    summed, columns sorted; isolated vertices get a zero row): the torch model's too
    (``meshseq.model.NeighborMean``)."""
    import scipy.sparse as sp

    deg = np.maximum(topology.degrees, 1).astype(np.float64)
    A = (sp.diags(1.0 / deg) @ topology.adjacency).tocsr()
    A.sum_duplicates()
    return A.astype(dtype)


def folded_input_norm(layer: tuple, offset: np.ndarray, spread: np.ndarray, ring) -> tuple:
    """The first conv layer ``(w_self, w_ring (C_in, C_out), bias (C_out,))`` with the input
    normalisation ``x' = (x - offset) / spread`` (offset ``(V, C_in)``, spread ``(C_in,)``) folded in:
    ``x' W1 + (A x') W2 + b = x W1' + (A x) W2' + b_v`` with ``W' = diag(1 / spread) W`` and the bias
    per vertex ``b_v = b - o W1 - (A o) W2`` ``(V, C_out)``, ``o = offset / spread``."""
    w_self, w_ring, bias = layer
    inv = 1.0 / np.asarray(spread, dtype=np.float64)
    o = np.asarray(offset, dtype=np.float64) * inv
    w1, w2 = w_self.astype(np.float64) * inv[:, None], w_ring.astype(np.float64) * inv[:, None]
    b = bias - o @ w_self.astype(np.float64) - (ring.astype(np.float64) @ o) @ w_ring.astype(np.float64)
    return w1.astype(np.float32), w2.astype(np.float32), b.astype(np.float32)


class NumpyNet:
    """``BDLSTM``'s inference (``step``, ``rollout``, ``initial_state``) on numpy arrays.

    Args:
        config: the checkpoint's ``ModelConfig``.
        tensors: ``{name: array}`` with the ``BDLSTM`` parameter and buffer names (``fc.weight``,
            ``convs.0.weight``, ``lstm.weight_ih_l0``, ...), float32.
        ring: ``ring_matrix(topology)``.
        threads: threads of the conv layers (blocks of vertices); default ``frame_threads()``.
        compiled: use the compiled mesh convolution (``meshseq.native``); default: where it builds.
    """

    def __init__(self, config: ModelConfig, tensors: dict, ring, threads: int | None = None,
                 compiled: bool | None = None):
        self.config = config
        t = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in tensors.items()}
        C, K = config.channels, config.conv_layers
        self.ring = ring
        self._ring_parts, self._pool = self._split_ring(ring, threads)
        self._bias_cache = {}  # (id of a conv bias, batch) -> its rows (``_bias_rows``)
        # (w_self, w_ring, bias) as right factors of (rows, C_in) views: encoder W1, W2 (C_in, C_out)
        convs = [(t[f"convs.{k}.weight"][:C], t[f"convs.{k}.weight"][C:], t[f"convs.{k}.bias"]) for k in range(K)]
        self.enc = list(convs)
        # decoder layer k: encoder layer K-1-k transposed, its own bias
        self.dec = [(np.ascontiguousarray(convs[K - 1 - k][0].T), np.ascontiguousarray(convs[K - 1 - k][1].T),
                     t[f"dec_conv_bias.{k}"]) for k in range(K)]
        self.fc_weight, self.fc_bias, self.dec_bias = t["fc.weight"], t["fc.bias"], t["dec_fc_bias"]
        self.mu = (t["fc_mu.weight"].T, t["fc_mu.bias"])
        self.lstms = [self._lstm_weights(t, "lstm")]
        if config.variant == "std-bd":
            self.lstms.append(self._lstm_weights(t, "lstm_backward"))
        self.scale = None if config.step_scale is None else np.asarray(config.step_scale, dtype=np.float32)
        self.norm = None
        if config.input_norm:  # (V, C) offset, (C,) spread: stored (C, V, 1), (C, 1, 1)
            norm = (np.ascontiguousarray(t["input_offset"][:, :, 0].T), t["input_spread"].reshape(-1))
            if K:  # folded into the first layer: no pass over the frames for it
                self.enc[0] = folded_input_norm(self.enc[0], *norm, ring)
            else:
                self.norm = norm
        self._setup_compiled(compiled, threads, ring)

    def _setup_compiled(self, compiled: bool | None, threads: int | None, ring) -> None:
        """The compiled library (``meshseq.native``), its threads, ring and the conv layers' maps as
        left factors ``(C_out, C_in)`` of channel-major frames; ``_lib`` None where it is not used."""
        from meshseq import native
        from meshseq.acap.features import frame_threads

        self._lib = native.conv_library() if compiled is None or compiled else None
        if compiled and self._lib is None:
            raise MeshseqError("the compiled mesh convolution is not available (see the warning above)")
        if self._lib is None:
            return
        self._threads = frame_threads() if threads is None else threads
        self._cring = native.CompiledRing(ring)
        self._compiled = {id(layer): (np.ascontiguousarray(layer[0].T), np.ascontiguousarray(layer[1].T))
                          for layer in self.enc + self.dec}

    @staticmethod
    def _split_ring(ring, threads: int | None):
        """``([(rows of A, their slice)], pool)``: one block of vertices per thread (pool None: one)."""
        from meshseq.acap.features import frame_threads

        V = ring.shape[0]
        n = max(1, min(frame_threads() if threads is None else threads, V // 1024))
        bounds = [V * i // n for i in range(n + 1)]
        parts = [(ring[a:b], slice(a, b)) for a, b in zip(bounds, bounds[1:])]
        if n == 1:
            return parts, None
        from concurrent.futures import ThreadPoolExecutor

        return parts, ThreadPoolExecutor(n)

    def _lstm_weights(self, t: dict, name: str) -> list[tuple]:
        """Per layer ``(W_ih^T (L_in, 4L), W_hh^T (L, 4L), b_ih + b_hh (4L,))``."""
        return [(t[f"{name}.weight_ih_l{k}"].T, t[f"{name}.weight_hh_l{k}"].T,
                 t[f"{name}.bias_ih_l{k}"] + t[f"{name}.bias_hh_l{k}"]) for k in range(self.config.lstm_layers)]

    # -- the pieces (vertex-major (V, B, C)) ----------------------------------------------------

    def channel_major(self, chains: int) -> bool:
        """Whether a batch of ``chains`` runs the compiled layers on channel-major frames ``(V, C, Bp)``:
        where they are built and the batch fills more than half a SIMD tile (``COMPILED_MIN_CHAINS``;
        below that numpy's layers are faster: one compiled pass costs the same for 1 chain as for 8)."""
        return self._lib is not None and chains >= COMPILED_MIN_CHAINS

    def _conv(self, x: np.ndarray, layer: tuple, act: bool, cm: bool) -> np.ndarray:
        """One mesh-conv layer on vertex-major frames (channel-major if ``cm``): ``x W1 + (A x) W2 + b``
        [tanh]."""
        if not cm:
            return self._numpy_conv(x, layer, act)
        from meshseq import native

        w_self, w_ring = self._compiled[id(layer)]
        return native.conv(self._lib, x, w_self, w_ring, layer[2], self._cring, act, self._threads)

    def _numpy_conv(self, x: np.ndarray, layer: tuple, act: bool) -> np.ndarray:
        """One mesh-conv layer ``(V, B, C_in)`` -> ``(V, B, C_out)`` in numpy, one block of vertices per
        thread (scipy's product and numpy release the GIL)."""
        w_self, w_ring, bias = layer
        V, B, C = x.shape
        C_out = w_self.shape[1]
        out = np.empty((V, B, C_out), dtype=np.float32)
        cols = x.reshape(V, B * C)
        bias_rows = self._bias_rows(bias, B)  # (B*C_out,) or per vertex (V, B*C_out)

        def rows(part: int) -> None:
            ring, r = self._ring_parts[part]
            y = out[r].reshape(-1, C_out)  # a view: the block's rows of out, written in place
            np.matmul(x[r].reshape(-1, C), w_self, out=y)
            y += (ring @ cols).reshape(-1, C) @ w_ring
            y_rows = out[r].reshape(-1, B * C_out)  # rows of B*C_out: a long inner loop for the bias
            y_rows += bias_rows if bias_rows.ndim == 1 else bias_rows[r]
            if act:
                np.tanh(y, out=y)

        self._map(rows)
        return out

    def _bias_rows(self, bias: np.ndarray, batch: int) -> np.ndarray:
        """A conv bias ``(C_out,)`` or per vertex ``(V, C_out)`` repeated for ``batch`` rows: ``(batch *
        C_out,)`` or ``(V, batch * C_out)`` (kept for the next call with this batch)."""
        key = (id(bias), batch)
        if key not in self._bias_cache:
            if len(self._bias_cache) >= 4 * (len(self.enc) + len(self.dec)):  # a few batch sizes at most
                self._bias_cache.clear()
            self._bias_cache[key] = np.ascontiguousarray(np.tile(bias, batch))
        return self._bias_cache[key]

    def _fc(self, x: np.ndarray, weight: np.ndarray, bias: np.ndarray) -> np.ndarray:
        """The decoder's FC ``x @ weight + bias``: ``(B, L) @ (L, N)`` -> ``(B, N)``, a block of the
        N output columns per thread (each thread streams its share of the weight; BLAS runs one
        thread per caller)."""
        out = np.empty((x.shape[0], weight.shape[1]), dtype=np.float32)
        bounds = np.linspace(0, weight.shape[1], len(self._ring_parts) + 1).astype(int)

        def cols(part: int) -> None:
            a, b = bounds[part], bounds[part + 1]
            np.matmul(x, weight[:, a:b], out=out[:, a:b])
            out[:, a:b] += bias[a:b]

        self._map(cols)
        return out

    def _fc_encode(self, xt: np.ndarray) -> np.ndarray:
        """The encoder's FC ``W x + b`` of columns ``xt`` ``(N, B)`` -> ``(B, L)``, a block of W's rows
        per thread (W ``(L, N)`` streamed row by row: BLAS takes a wide row-major weight as the left
        factor 2-3x faster than its transpose as the right one)."""
        weight = self.fc_weight
        out = np.empty((weight.shape[0], xt.shape[1]), dtype=np.float32)
        bounds = np.linspace(0, weight.shape[0], len(self._ring_parts) + 1).astype(int)

        def rows(part: int) -> None:
            a, b = bounds[part], bounds[part + 1]
            np.matmul(weight[a:b], xt, out=out[a:b])

        self._map(rows)
        return out.T + self.fc_bias

    def _map(self, work) -> None:
        """``work(part)`` for every block (``_split_ring``), on the pool when there is one."""
        if self._pool is None:
            work(0)
        else:
            list(self._pool.map(work, range(len(self._ring_parts))))

    def _encode(self, x: np.ndarray, n: int, cm: bool) -> np.ndarray:
        """Vertex-major frames -> ``mu`` ``(n, L)`` of the first ``n`` chains."""
        if self.norm is not None:
            offset, spread = self.norm
            x = (x - offset[:, :, None]) / spread[:, None] if cm else (x - offset[:, None]) / spread
        for layer in self.enc:
            x = self._conv(x, layer, True, cm)
        if not cm:
            V, B, C = x.shape
            e = self._fc_encode(np.ascontiguousarray(x.transpose(1, 0, 2)).reshape(B, V * C).T)[:n]
        else:  # (V*C, Bp): the FC's columns as they lie
            from meshseq import native

            e = native.fc_wx(self._lib, self.fc_weight, x.reshape(-1, x.shape[-1]), self.fc_bias, self._threads).T[:n]
        mu = e @ self.mu[0]
        mu += self.mu[1]
        if self.config.mu_max is not None:
            m = np.float32(self.config.mu_max)
            mu = m * np.tanh(mu / m)
        return mu

    def _decode(self, h: np.ndarray, cm: bool) -> np.ndarray:
        """``(B, L)`` -> ``dX`` vertex-major (tied FC, decoder convs; no tanh after the last)."""
        B, V, C = h.shape[0], self.config.n_vertices, self.config.channels
        y = self._to_vm(self._fc(h, self.fc_weight, self.dec_bias).reshape(B, V, C), cm)
        K = len(self.dec)
        for k, layer in enumerate(self.dec):
            y = self._conv(y, layer, k < K - 1, cm)
        return y

    def _to_vm(self, x: np.ndarray, cm: bool) -> np.ndarray:
        """Frames ``(B, V, C)`` -> vertex-major: ``(V, B, C)``, or if ``cm`` ``(V, C, Bp)`` with zero
        padding."""
        x = np.asarray(x, dtype=np.float32)
        if not cm:
            return np.ascontiguousarray(x.transpose(1, 0, 2))
        from meshseq import native

        B, V, C = x.shape
        out = np.zeros((V, C, native.padded_chains(B)), dtype=np.float32)
        native.transpose(self._lib, np.ascontiguousarray(x).reshape(B, V * C), out.reshape(V * C, -1)[:, :B],
                         self._threads)
        return out

    @staticmethod
    def _from_vm(x: np.ndarray, n: int, cm: bool) -> np.ndarray:
        """Vertex-major frames -> ``(n, V, C)`` (a view) of the first ``n`` chains."""
        return x[:, :, :n].transpose(2, 0, 1) if cm else x.transpose(1, 0, 2)

    def _write_frames(self, x: np.ndarray, n: int, cm: bool, out: np.ndarray) -> None:
        """Vertex-major frames of ``n`` chains into ``out`` ``(n, V*C)`` (rows of unit stride)."""
        if not cm:
            out[...] = x.transpose(1, 0, 2).reshape(n, -1)
            return
        from meshseq import native

        native.transpose(self._lib, x.reshape(-1, x.shape[-1])[:, :n], out, self._threads)

    def _lstm_rows(self, weights: list, z: np.ndarray, h: np.ndarray, c: np.ndarray):
        """Layers of one LSTM for ``z`` ``(B, L)``, ``h``, ``c`` ``(K, B, L)`` -> ``(out, h', c')``."""
        L = h.shape[-1]
        hs, cs, x = [], [], z
        for k, (w_ih, w_hh, b) in enumerate(weights):
            g = x @ w_ih
            g += h[k] @ w_hh
            g += b
            _sigmoid(g[:, : 2 * L])
            _sigmoid(g[:, 3 * L:])
            np.tanh(g[:, 2 * L: 3 * L], out=g[:, 2 * L: 3 * L])
            ck = g[:, L: 2 * L] * c[k]
            ck += g[:, :L] * g[:, 2 * L: 3 * L]
            x = g[:, 3 * L:] * np.tanh(ck)
            hs.append(x)
            cs.append(ck)
        return x, np.stack(hs), np.stack(cs)

    def _lstm(self, z: np.ndarray, state, n_forward: int | None):
        """One step of the LSTM(s): rows ``n_forward:`` use the backward LSTM (std-bd)."""
        h, c = state
        if len(self.lstms) == 1 or n_forward is None or n_forward >= len(z):
            out, h2, c2 = self._lstm_rows(self.lstms[0], z, h, c)
            return out, (h2, c2)
        f, b = slice(0, n_forward), slice(n_forward, None)
        parts = [self._lstm_rows(w, z[r], h[:, r], c[:, r]) for w, r in ((self.lstms[0], f), (self.lstms[1], b))]
        return (np.concatenate([p[0] for p in parts]),
                (np.concatenate([p[1] for p in parts], 1), np.concatenate([p[2] for p in parts], 1)))

    def _step_vm(self, state, x: np.ndarray, n_forward: int | None, cm: bool):
        """``(state, x)`` -> ``(state', x + dX)`` on vertex-major frames, channel-major if ``cm``
        (padded chains stay zero)."""
        n = state[0].shape[1]
        mu = self._encode(x, n, cm)
        out, state = self._lstm(mu, state, n_forward)
        d = self._decode(out, cm)
        if self.scale is not None:
            d *= self.scale[:, None] if cm else self.scale
        d += x
        if cm and d.shape[-1] > n:
            d[:, :, n:] = 0.0
        return state, d

    # -- public, batch-major (as BDLSTM) --------------------------------------------------------

    def initial_state(self, n_forward: int, n_backward: int = 0):
        """``(h, c)``, each ``(K, n_forward + n_backward, L)`` float32: +init forward rows, -init after."""
        K, L, v = self.config.lstm_layers, self.config.latent, np.float32(self.config.init_state)
        sign = np.concatenate([np.ones(n_forward, np.float32), -np.ones(n_backward, np.float32)])
        s = np.ascontiguousarray(np.broadcast_to((v * sign)[None, :, None], (K, len(sign), L)))
        return s, s.copy()

    def encode(self, x: np.ndarray) -> np.ndarray:
        """Frames ``(B, V, C)`` -> latent means ``mu`` ``(B, L)``."""
        cm = self.channel_major(len(x))
        return self._encode(self._to_vm(x, cm), len(x), cm)

    def decode(self, h: np.ndarray) -> np.ndarray:
        """LSTM outputs ``(B, L)`` -> frame changes ``dX`` ``(B, V, C)``."""
        cm = self.channel_major(len(h))
        return self._from_vm(self._decode(np.asarray(h, dtype=np.float32), cm), len(h), cm)

    def step(self, state, x: np.ndarray, n_forward: int | None = None, sample: bool = False):
        """G(s, X) -> ``(s', X + dX)`` for frames ``(B, V, C)`` float32 (``sample``: not here)."""
        if sample:
            raise MeshseqError("drawing the VAE latent (sampled predictions) needs the torch model")
        cm = self.channel_major(len(x))
        state, nxt = self._step_vm(state, self._to_vm(x, cm), n_forward, cm)
        return state, self._from_vm(nxt, len(x), cm)

    def rollout(self, first: np.ndarray, steps: int, state, n_forward: int | None = None):
        """Free-running frames ``(B, steps + 1, V, C)`` from ``first`` ``(B, V, C)``; and the final state."""
        first = np.asarray(first, dtype=np.float32)
        cm = self.channel_major(len(first))
        x = self._to_vm(first, cm)
        frames = np.empty((len(first), steps + 1) + first.shape[1:], dtype=np.float32)
        frames[:, 0] = first
        rows = frames.reshape(len(first), steps + 1, -1)  # a view: frames is contiguous
        for t in range(steps):  # the time loop is the only Python loop
            state, x = self._step_vm(state, x, n_forward, cm)
            self._write_frames(x, len(first), cm, rows[:, t + 1])
        return frames, state

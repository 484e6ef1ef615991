"""The roll-out's fast path: fused mesh-convolution layers with a hand-written backward.

What it fuses, and why. A mesh-conv layer on vertex-major frames ``x`` ``(V, C, B)`` (vertex,
channel, window) is ``y = act(W_s x + W_r (A x) + b) [+ r]`` (``W_s``/``W_r`` the self and ring
channel maps ``(C_out, C_in)``, ``A`` the row-normalised 1-ring mean, ``act`` tanh or none, ``r``
an optional residual: the decoder's last layer adds the current frame, ``X_t+1 = X_t + dX``).
The ring mean acts on vertices only, so ``A (W_r x) = W_r (A x)``. Written as plain torch ops
with autograd (``MeshConv.forward``, the readable reference) one layer costs about ten
full-size passes forward and more backward. ``MeshConvFused`` (one layer) saves only ``x`` and
the activation's output; ``MeshConvStack`` (the roll-out's encoder and decoder: several layers
as one autograd node) also lets each layer hand the one below the gradient of its
pre-activation, so a tanh layer's backward needs no pass of its own for tanh's derivative. Two
implementations of the same arithmetic:

* CPU, float32: ``csrc/mesh_conv.cpp``, compiled on first use with the machine's C++ compiler
  (``torch.utils.cpp_extension``; cached in ``meshseq_kernels-PY-TORCH-CPU-CHECKOUT`` under
  ``TORCH_EXTENSIONS_DIR``, by default ``~/.cache/torch_extensions``). Forward: each vertex gathers its neighbours' ``(C, B)`` blocks
  (rows of the vertex-major layout), applies both maps, the bias, tanh and the residual while the
  block is in registers, vectorised over the windows: ``x`` read once, ``y`` written once.
  Backward: ``gx = W_s^T g + W_r^T (A^T g)`` and the weight gradients in one more pass, summed
  per fixed vertex chunk so that the bits do not depend on the thread count. Measured on the
  horse (8431 vertices, 16 windows, 2 threads, 10th percentile of 150): 0.7 ms forward with
  tanh, 1.1-1.6 ms backward per layer (the machine's speed drifts), against 4.4 + 6.6 ms (1
  thread) for the torch-op version of the channel-major layout it replaced.
* elsewhere (CUDA, float64, no compiler, or ``MESHSEQ_CPU_KERNELS=0``): the same layer as a few
  torch operators (``embedding_bag`` ring means on the ``(V, C*B)`` table, broadcast matmuls for
  the maps).

Both agree with ``MeshConv.forward`` to float32 rounding (``tests/test_kernels.py``).

The big FC's per-step products (``fc_product``: ``W x``, ``fc_transposed_product``: ``W^T h``;
``W`` ``(L, V*C)``, 39 MB on the horse, against 16 columns) run in ``csrc/fc.cpp`` on CPU in
float32: each product is one stream over ``W``, each weight broadcast against a SIMD vector of
the columns (2.0 ms a product on the horse, 2 threads: about the time to read ``W`` from memory);
BLAS ran these skinny shapes at a third to a half of that rate (see that file). Its weight
gradient over a roll-out (``fc_weight_gradient``) sums each weight's terms in registers, reading
the roll-out's frames where they lie. The same code runs on AVX2 (two registers a 16-window tile; smaller register tiles there).

The LSTM steps (``LSTMStep``, ``csrc/lstm.cpp``): all layers of a step as one autograd node, the
small products register-tiled (BLAS repacked the weights at every call), the gates in one pass.

The window losses' per-frame squared errors (``frame_errors_of_frames``: L_rec of both chains,
L_bd and L_motion's step sizes) run in ``csrc/frame_errors.cpp`` on CPU in float32, read from the
roll-out's own vertex-major frames: one pass forward, one backward (each frame's gradient in its
own layout), instead of about 25 passes of torch operators over ``(B, n, V, C)`` tensors and a
stacked copy of the chains.
"""

from __future__ import annotations

import os
import sys
import threading
import warnings
from pathlib import Path

import torch
import torch.nn.functional as F

from meshseq.native import cpu_signature

_CSRC = Path(__file__).resolve().parent / "csrc"
_SOURCES = [_CSRC / name for name in ("mesh_conv.cpp", "fc.cpp", "frame_errors.cpp", "lstm.cpp")]
_HEADERS = [_CSRC / "simd.h", _CSRC / "conv_forward.h", _CSRC / "fc_forward.h"]  # included by the sources; torch's build cache hashes only sources and flags
_lock = threading.Lock()
_cpu_kernels: bool | None = None  # None: not tried yet


def cpu_kernels_available() -> bool:
    """Build (first call; about 30 s) or load the C++ CPU kernels; False, with one warning, if that fails.

    ``MESHSEQ_CPU_KERNELS=0`` turns them off (the torch-op path is used everywhere).
    """
    global _cpu_kernels
    if _cpu_kernels is not None:
        return _cpu_kernels
    with _lock:
        if _cpu_kernels is not None:
            return _cpu_kernels
        if os.environ.get("MESHSEQ_CPU_KERNELS", "1") == "0":
            _cpu_kernels = False
            return False
        try:
            from torch.utils.cpp_extension import get_default_build_root, load

            py = f"py{sys.version_info[0]}{sys.version_info[1]}"
            root = os.environ.get("TORCH_EXTENSIONS_DIR") or get_default_build_root()  # as torch's own builds
            import hashlib

            # one folder per checkout (torch's build rebuilds whenever the sources' path changes: two
            # checkouts sharing one folder rebuilt it in turn, and a build killed midway left its lock)
            where = hashlib.sha1(str(_CSRC).encode()).hexdigest()[:8]
            build = Path(root) / f"meshseq_kernels-{py}-torch{torch.__version__}-{cpu_signature()}-{where}"
            build.mkdir(parents=True, exist_ok=True)
            wait_for_build_lock(build)

            headers = hashlib.sha1(b"".join(p.read_bytes() for p in _HEADERS)).hexdigest()[:12]
            flags = ["-O3", "-march=native", "-fopenmp", f"-DMESHSEQ_HEADERS={headers}"]  # a header change rebuilds
            load("meshseq_kernels", [str(p) for p in _SOURCES], extra_cflags=flags,
                 extra_ldflags=["-fopenmp"], build_directory=str(build), is_python_module=False, verbose=False)
            _cpu_kernels = all(hasattr(torch.ops.meshseq, op) for op in ("conv_forward", "fc_wx", "fc_wtx", "frame_errors",
                                                                        "lstm_forward"))
        except Exception as e:  # no compiler, no ninja, a compile error: fall back, say why
            reason = " ".join(str(e).split())[:300]
            warnings.warn(f"meshseq: the C++ CPU kernels could not be built ({type(e).__name__}: {reason}); "
                          "training on CPU uses the slower torch-op path", RuntimeWarning, stacklevel=2)
            _cpu_kernels = False
    return _cpu_kernels


def clear_stale_lock(build: Path, max_age_s: float = 600.0) -> bool:
    """Remove ``build/lock`` if it is older than ``max_age_s`` (a build takes about 30 s).

    torch's extension builder waits, without end, for the lock file a build leaves while it
    runs; a build that was killed (Ctrl-C, a session's end) leaves it behind. True if removed.
    """
    import time

    lock = build / "lock"
    try:
        if time.time() - lock.stat().st_mtime > max_age_s:
            lock.unlink()
            warnings.warn(f"meshseq: removed a stale build lock {lock} (a killed build)", RuntimeWarning, stacklevel=2)
            return True
    except FileNotFoundError:
        pass
    return False


def wait_for_build_lock(build: Path, max_age_s: float = 600.0, poll_s: float = 1.0) -> float:
    """Wait while another process builds the kernels in ``build`` (its ``lock`` file exists), saying so
    once; a lock older than ``max_age_s`` is a killed build's and is removed (``clear_stale_lock``).

    torch's own wait has no end, and when the lock of a killed build goes it loads a build that was
    never finished (and meshseq falls back to the slow path). Returns the seconds waited.
    """
    import time

    lock, start, said = build / "lock", time.monotonic(), False
    while lock.exists() and not clear_stale_lock(build, max_age_s):
        if not said:
            warnings.warn(f"meshseq: waiting for another process's kernel build ({lock}); a lock older than "
                          f"{max_age_s / 60:g} minutes is taken for a killed build's and removed", RuntimeWarning,
                          stacklevel=3)
            said = True
        time.sleep(poll_s)
    return time.monotonic() - start


def _use_cpu_kernels(x: torch.Tensor) -> bool:
    return x.device.type == "cpu" and x.dtype == torch.float32 and cpu_kernels_available()


def _use_fc_kernels(weight: torch.Tensor, x: torch.Tensor) -> bool:
    return (weight.dtype == torch.float32 and x.dtype == torch.float32 and x.shape[1] % 8 == 0
            and _use_cpu_kernels(weight))


def fc_product(weight: torch.Tensor, x: torch.Tensor, bias: torch.Tensor | None = None) -> torch.Tensor:
    """``W x (+ bias[:, None])``: the big FC ``W`` ``(L, N)`` times few columns ``x`` ``(N, B)`` -> ``(L, B)``.

    On CPU in float32 with B a multiple of 8: ``csrc/fc.cpp`` (one stream over W; 2.5 against
    4.0 ms on the horse, 16 columns, 2 threads); otherwise ``torch.addmm``/``mm`` (other
    dtypes, e.g. the bfloat16 weight of ``--precision bf16``, compute in ``weight``'s dtype).
    """
    if _use_fc_kernels(weight, x):
        return torch.ops.meshseq.fc_wx(weight, x.contiguous(), bias)
    x = x.to(weight.dtype)
    return torch.mm(weight, x) if bias is None else torch.addmm(bias.to(weight.dtype)[:, None], weight, x)


def fc_product_and_row_sums(weight: torch.Tensor, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(W x, x.sum(1))``: ``fc_product`` and the row sums of ``x`` ``(N, B)`` -> ``(N,)`` (the decoder's
    backward: its bias gradient), on CPU in float32 from ``x``'s chunks while ``fc.cpp`` has them in
    cache (a separate sum read ``x`` again: about 0.3 ms a step on the horse)."""
    if _use_fc_kernels(weight, x):
        out, sums = torch.ops.meshseq.fc_wx_row_sums(weight, x.contiguous())
        return out, sums
    return fc_product(weight, x), x.sum(1)


def fc_transposed_product(weight: torch.Tensor, h: torch.Tensor, bias: torch.Tensor | None = None) -> torch.Tensor:
    """``W^T h (+ bias[:, None])``: the tied decoder's product, ``W`` ``(L, N)``, ``h`` ``(L, B)`` -> ``(N, B)``.

    As ``fc_product``: ``csrc/fc.cpp`` on CPU in float32 (2.5 against 5.2 ms on the horse),
    otherwise ``torch.mm`` in ``weight``'s dtype.
    """
    if _use_fc_kernels(weight, h):
        return torch.ops.meshseq.fc_wtx(weight, h.contiguous(), bias)
    h = h.to(weight.dtype)
    return torch.mm(weight.t(), h) if bias is None else torch.addmm(bias.to(weight.dtype)[:, None], weight.t(), h)


def fc_weight_gradient_supported(left: torch.Tensor, rights: list[torch.Tensor]) -> bool:
    """Whether ``fc_weight_gradient`` runs ``csrc/fc.cpp`` for these pairs (CPU float32, L
    in 16, 32, 64, 128, 256); otherwise the caller forms the gradient with torch (``model._GradBank``)."""
    return (left.dtype == torch.float32 and _use_cpu_kernels(left)
            and torch.ops.meshseq.fc_weight_grad_supports(left.shape[1])
            and all(r.dtype == torch.float32 and r.device == left.device for r in rights))


def fc_weight_gradient(left: torch.Tensor, rights: list[torch.Tensor]) -> torch.Tensor:
    """``sum_t left_t^T right_t^T`` ``(L, N)``: the big FC weight's gradient from a roll-out's pairs.

    ``left`` ``(sum_t B_t, L)``: the pairs' left factors stacked in order; ``rights``: their ``(N,
    B_t)`` right factors (frames, as the roll-out keeps them). ``csrc/fc.cpp`` sums every weight's
    gradient in registers over all pairs, reading each right once where it lies: no concatenated
    ``(N, sum_t B_t)`` copy (301 MB on the horse) and no transposing copy of an ``(N, L)`` product
    into the weight's layout. The same bits with any thread count. CPU float32 only
    (``fc_weight_gradient_supported``).
    """
    return torch.ops.meshseq.fc_weight_grad(left.contiguous(), [r.contiguous() for r in rights])


def lstm_step_supported(lstm, z: torch.Tensor) -> bool:
    """Whether ``lstm_step`` runs ``csrc/lstm.cpp`` for this ``nn.LSTM`` and input: CPU, float32, no
    autocast, biases, no projection, input and hidden widths multiples of 16."""
    return (z.dtype == torch.float32 and not torch.is_autocast_enabled(z.device.type) and lstm.bias
            and not lstm.proj_size and z.shape[-1] % 16 == 0 and lstm.hidden_size % 16 == 0
            and all(p.dtype == torch.float32 and p.device == z.device for p in lstm.parameters())
            and _use_cpu_kernels(z))


def lstm_transposed(lstm) -> tuple[list, list, list]:
    """What ``csrc/lstm.cpp``'s forward reads, made once per roll-out (no gradient: the step's
    backward returns the gradients of the weights themselves): per layer ``W_ih^T``, ``W_hh^T`` and
    ``b_ih + b_hh``."""
    with torch.no_grad():
        layers = range(lstm.num_layers)
        return ([getattr(lstm, f"weight_ih_l{k}").t().contiguous() for k in layers],
                [getattr(lstm, f"weight_hh_l{k}").t().contiguous() for k in layers],
                [getattr(lstm, f"bias_ih_l{k}") + getattr(lstm, f"bias_hh_l{k}") for k in layers])


class LSTMStep(torch.autograd.Function):
    """One step of a stacked ``nn.LSTM``, all layers, as one autograd node (``csrc/lstm.cpp``):
    ``z`` ``(B, I)``, ``h``, ``c`` ``(K, B, H)`` -> ``(h', c')``; ``transposed``: ``lstm_transposed``;
    ``params``: per layer ``w_ih, w_hh, b_ih, b_hh``."""

    @staticmethod
    def forward(ctx, z, h, c, transposed, *params):
        z, h, c = z.contiguous(), h.contiguous(), c.contiguous()
        h_out, c_out, gates = torch.ops.meshseq.lstm_forward(z, h, c, *transposed)
        ctx.save_for_backward(z, h, c, h_out, c_out, gates, *params[0::4], *params[1::4])
        return h_out, c_out

    @staticmethod
    def backward(ctx, dh_out, dc_out):
        z, h, c, h_out, c_out, gates, *weights = ctx.saved_tensors
        K = len(weights) // 2
        res = torch.ops.meshseq.lstm_backward(dh_out.contiguous(), dc_out.contiguous(), z, h, c, h_out, c_out,
                                              gates, weights[:K], weights[K:])
        grads = []
        for k in range(K):
            dwi, dwh, db = res[3 + 3 * k: 6 + 3 * k]
            grads += [dwi, dwh, db, db.clone()]  # b_ih and b_hh: the same gradient, one tensor each
        return (res[0], res[1], res[2], None, *grads)


class _FrameErrors(torch.autograd.Function):
    """``csrc/frame_errors.cpp`` with autograd; see ``frame_errors_of_frames``."""

    @staticmethod
    def forward(ctx, windows, steps, *frames):
        w = windows.reshape(windows.shape[0], windows.shape[1], -1)
        ctx.save_for_backward(w, *frames)
        return torch.ops.meshseq.frame_errors(list(frames), w, steps)

    @staticmethod
    def backward(ctx, ge):
        w, *frames = ctx.saved_tensors
        need = [i for i in range(len(frames)) if ctx.needs_input_grad[2 + i]]
        grads: list = [None] * len(frames)
        for i, g in zip(need, torch.ops.meshseq.frame_errors_backward(ge, frames, w, need)):
            grads[i] = g
        return (None, None, *grads)


def frame_error(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``||a - b||^2`` per frame: ``(B, n, V, C)`` pairs -> ``(B, n)`` (torch operators)."""
    return (a - b).square().sum((-2, -1))


class _StackFrames(torch.autograd.Function):
    """``torch.stack([f.permute(2, 0, 1) for f in frames], 1)``: vertex-major frames ``(V, C, B)``
    -> ``(B, n, V, C)``, with a backward that hands each frame a contiguous vertex-major gradient.

    (Plain ``stack`` gives each frame a strided view of the ``(B, n, V, C)`` gradient; adding it to
    the frame's other gradients, from the encoder and the residual, then ran on strided memory:
    1.3 ms an add on the horse against 0.35 for contiguous tensors, and a copy of 1.3 ms more.)
    """

    @staticmethod
    def forward(ctx, *frames):
        return torch.stack([f.permute(2, 0, 1) for f in frames], 1)

    @staticmethod
    def backward(ctx, g):
        return tuple(g[:, i].permute(1, 2, 0).contiguous() if ctx.needs_input_grad[i] else None
                     for i in range(g.shape[1]))


def stack_frames(frames: list[torch.Tensor]) -> torch.Tensor:
    """Vertex-major frames ``(V, C, B)`` (a roll-out's steps) -> ``(B, n, V, C)``, contiguous."""
    return _StackFrames.apply(*frames)


def frame_errors_of_frames(frames: list[torch.Tensor], windows: torch.Tensor, steps: bool = False) -> torch.Tensor:
    """``frame_errors`` of a roll-out's vertex-major frames: ``frames`` ``n`` tensors ``(V, C, R)``
    (lanes: the ``B`` forward chains, then, when ``R = 2B``, the backward chains), as
    ``BDLSTM.forward`` makes them (its ``"frames"``).

    On CPU in float32 one C++ pass forward and one backward (``csrc/frame_errors.cpp``), each
    frame's gradient in its own layout, with no stacked copy of the chains either way (the stack
    and the transposes of its gradient took about 40 ms an iteration on the horse); elsewhere the
    frames are stacked and the torch operators run.
    """
    if (all(f.dtype == torch.float32 for f in frames) and windows.dtype == torch.float32
            and not windows.requires_grad and _use_cpu_kernels(frames[0])):
        return _FrameErrors.apply(windows.contiguous(), steps, *(f.contiguous() for f in frames))
    return _frame_errors_torch(stack_frames(frames), windows, steps)


def frame_errors(chains: torch.Tensor, windows: torch.Tensor, steps: bool = False) -> torch.Tensor:
    """Per-frame squared errors of a roll-out: ``(3, B, n)``, rows ``||f_i - x_i||^2``,
    ``||g_i - x_{n-1-i}||^2``, ``||f_i - g_{n-1-i}||^2`` (the last two zero without backward chains);
    with ``steps`` ``(6, B, n)``, also the squared step sizes ``||f_i - f_{i-1}||^2``,
    ``||g_i - g_{i-1}||^2``, ``||x_i - x_{i-1}||^2`` (zero at ``i = 0``; L_motion's).

    ``chains`` ``(R, n, V, C)``: the forward chains ``f`` (rows ``:B``), then, when ``R = 2B``,
    the backward chains ``g`` in their own order; ``windows`` ``(B, n, V, C)``: the truth ``x``.
    On CPU in float32 the chains are cut into vertex-major frames for ``frame_errors_of_frames``'s
    C++ pass (training reads the roll-out's frames directly); elsewhere torch operators.
    """
    if (chains.dtype == torch.float32 and windows.dtype == torch.float32 and not windows.requires_grad
            and _use_cpu_kernels(chains)):
        return frame_errors_of_frames([chains[:, i].permute(1, 2, 0).contiguous() for i in range(chains.shape[1])],
                                      windows, steps)
    return _frame_errors_torch(chains, windows, steps)


def _frame_errors_torch(chains: torch.Tensor, windows: torch.Tensor, steps: bool) -> torch.Tensor:
    """``frame_errors`` as torch operators (any device and dtype)."""
    B = windows.shape[0]

    def step_sizes(a):  # (B, n), zero first
        return F.pad(frame_error(a[:, 1:], a[:, :-1]), (1, 0))

    f = chains[:B]
    rows = [frame_error(f, windows)]
    zero = torch.zeros_like(rows[0])
    if chains.shape[0] == B:
        rows += [zero, zero]
        if steps:
            rows += [step_sizes(f), zero, step_sizes(windows)]
        return torch.stack(rows)
    g = chains[B:]
    rows += [frame_error(g, windows.flip(1)), frame_error(f, g.flip(1))]
    if steps:
        rows += [step_sizes(f), step_sizes(g), step_sizes(windows)]
    return torch.stack(rows)


def ring_mean(ring, x: torch.Tensor, transpose: bool = False) -> torch.Tensor:
    """The 1-ring mean ``A x`` (or ``A^T x``) of vertex-major ``x`` ``(V, ...)``, same shape out.

    One ``embedding_bag`` (weighted sum of table rows) over the ``(V, rest)`` table: each
    neighbour entry reads one contiguous row. ``ring``: a ``NeighborMean`` (its CSR ``A``, ``At``).
    """
    M = ring.At if transpose else ring.A
    table = x.reshape(x.shape[0], -1)
    out = F.embedding_bag(M.col_indices(), table, M.crow_indices(), mode="sum",
                          per_sample_weights=M.values().to(table.dtype), include_last_offset=True)
    return out.view(x.shape)


def ring_csr(ring, transpose: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(row pointers, columns, weights)`` of ``ring.A`` (or ``ring.At``), what the C++ layers read;
    kept on the ring until its matrix changes (e.g. moved to another device): three accessor calls
    per layer call were a few ms an iteration."""
    M = ring.At if transpose else ring.A
    cache = ring.__dict__.setdefault("_csr_arrays", {})
    hit = cache.get(transpose)
    if hit is None or hit[0] is not M:
        hit = cache[transpose] = (M, M.crow_indices(), M.col_indices(), M.values())
    return hit[1:]


def _layer_forward(x, w_self, w_ring, bias, ring, act: bool, residual, cpp: bool) -> torch.Tensor:
    """One layer ``act(W_s x + W_r (A x) + b) [+ residual]`` on contiguous ``(V, C_in, B)``; ``bias``
    ``(C_out,)``, or ``(V, C_out)`` (one per vertex)."""
    if cpp:
        return torch.ops.meshseq.conv_forward(x, w_self, w_ring, bias, *ring_csr(ring), act, residual)
    y = torch.matmul(w_self, x).add_(torch.matmul(w_ring, ring_mean(ring, x))).add_(bias.unsqueeze(-1))
    if act:
        y.tanh_()
    if residual is not None:
        y.add_(residual)
    return y


def _layer_backward(g, y, x, w_self, w_ring, ring, input_tanh: bool, cpp: bool, vertex_bias: bool = False):
    """``(gx, g_w_self, g_w_ring, g_bias)`` of one layer from ``g``, the gradient of its output;
    ``y``: its output when it has tanh (``g`` is then multiplied by ``1 - y^2`` first), None when it
    has none or ``g`` is already its pre-activation's gradient; ``input_tanh``: ``x`` is a tanh
    output, and ``gx`` comes back times ``1 - x^2`` (the layer below's pre-activation gradient);
    ``vertex_bias``: the layer's bias is ``(V, C_out)``, and so is ``g_bias`` (the lanes' sums)."""
    if cpp:
        if vertex_bias:
            if y is not None:
                g = torch.ops.aten.tanh_backward(g, y)
            gx, gws, gwr, _ = torch.ops.meshseq.conv_backward(g.contiguous(), None, x, w_self, w_ring,
                                                               *ring_csr(ring, True), input_tanh)
            return gx, gws, gwr, g.sum(2)
        return torch.ops.meshseq.conv_backward(g.contiguous(), y, x, w_self, w_ring, *ring_csr(ring, True), input_tanh)
    if y is not None:
        g = torch.ops.aten.tanh_backward(g, y)
    atg = ring_mean(ring, g.contiguous(), transpose=True)  # dL/d(A x)
    gx = torch.matmul(w_self.t(), g).add_(torch.matmul(w_ring.t(), atg))
    if input_tanh:
        gx = torch.ops.aten.tanh_backward(gx, x)
    gws = torch.einsum("vob,vcb->oc", g, x)
    gwr = torch.einsum("vob,vcb->oc", atg, x)
    return gx, gws, gwr, g.sum(2) if vertex_bias else g.sum((0, 2))


class MeshConvFused(torch.autograd.Function):
    """``y = act(W_s x + W_r (A x) + b) [+ residual]`` on ``(V, C_in, B)`` -> ``(V, C_out, B)``.

    ``ring``: the ``NeighborMean`` whose operator the layer applies. ``w_self``, ``w_ring``:
    ``(C_out, C_in)``; ``bias``: ``(C_out,)``; ``act``: apply tanh; ``residual``: ``(V, C_out, B)``
    added after (only without ``act``).
    """

    @staticmethod
    @torch.autocast("cpu", enabled=False)
    @torch.autocast("cuda", enabled=False)
    def forward(ctx, x, w_self, w_ring, bias, ring, act: bool, residual):
        """Always float32 (memory-bound: bfloat16 would save little and lose precision)."""
        if act and residual is not None:
            raise ValueError("MeshConvFused: a residual after tanh is not supported")
        x = x.contiguous()
        cpp = _use_cpu_kernels(x)
        y = _layer_forward(x, w_self, w_ring, bias, ring, act, residual, cpp)
        ctx.ring, ctx.act, ctx.cpp, ctx.has_residual = ring, act, cpp, residual is not None
        ctx.save_for_backward(x, w_self, w_ring, y if act else None)
        return y

    @staticmethod
    def backward(ctx, gy):
        x, w_self, w_ring, y = ctx.saved_tensors
        gres = gy if ctx.has_residual else None
        gx, gws, gwr, gb = _layer_backward(gy, y, x, w_self, w_ring, ctx.ring, False, ctx.cpp)
        return gx, gws, gwr, gb, None, None, gres


class MeshConvStack(torch.autograd.Function):
    """Several fused layers in a row as one autograd node: ``x`` ``(V, C, B)`` through layer k =
    ``act_k(W_s x + W_r (A x) + b_k)``, ``residual`` ``(V, C_out, B)`` (or None) added after the last
    (whose ``act`` must then be False).

    ``params``: ``w_self, w_ring, bias`` of each layer in order (a bias ``(C_out,)``, or ``(V, C_out)``:
    one per vertex, how the encoder's first layer folds in the input normalisation,
    ``model._normalizing_layer``); ``acts``: a tuple of bools, one per layer. The same arithmetic
    as ``MeshConvFused`` layer by layer; the backward differs in one place: a layer whose input is
    the previous layer's tanh output returns its input gradient already times ``1 - x^2`` (the C++
    kernel multiplies while it writes it), so the layers below the top need no tanh-derivative
    pass of their own over (gradient, output).
    """

    @staticmethod
    @torch.autocast("cpu", enabled=False)
    @torch.autocast("cuda", enabled=False)
    def forward(ctx, x, residual, ring, acts: tuple, *params):
        K = len(acts)
        if len(params) != 3 * K:
            raise ValueError(f"MeshConvStack: {K} layers need {3 * K} parameters, got {len(params)}")
        if acts[-1] and residual is not None:
            raise ValueError("MeshConvStack: a residual after tanh is not supported")
        x = x.contiguous()
        cpp = _use_cpu_kernels(x)
        inputs = []
        for k in range(K):
            inputs.append(x)
            x = _layer_forward(x, *params[3 * k: 3 * k + 3], ring, acts[k], residual if k == K - 1 else None, cpp)
        ctx.ring, ctx.acts, ctx.cpp, ctx.has_residual = ring, tuple(acts), cpp, residual is not None
        ctx.save_for_backward(*inputs, x if acts[-1] else None, *params)
        return x

    @staticmethod
    def backward(ctx, gy):
        K = len(ctx.acts)
        saved = ctx.saved_tensors
        inputs, y_top, params = saved[:K], saved[K], saved[K + 1:]
        grads: list = [None] * (3 * K)
        g = gy
        for k in reversed(range(K)):
            w_self, w_ring = params[3 * k], params[3 * k + 1]
            y = y_top if k == K - 1 else None  # below the top, g is already the pre-activation's gradient
            input_tanh = k > 0 and ctx.acts[k - 1]
            g, gws, gwr, gb = _layer_backward(g, y, inputs[k], w_self, w_ring, ctx.ring, input_tanh, ctx.cpp,
                                              vertex_bias=params[3 * k + 2].dim() == 2)
            grads[3 * k: 3 * k + 3] = [gws, gwr, gb]
        return (g, gy if ctx.has_residual else None, None, None, *grads)


_ALLOCATOR_TUNED = False


def keep_freed_memory() -> bool:
    """Let glibc's malloc keep and reuse freed blocks instead of unmapping them (CPU training).

    A roll-out allocates and frees thousands of 5 MB tensors per iteration, and the loss a few
    dozen of 75 MB. glibc serves large blocks with mmap (or trims them off the heap top), and
    every fresh one costs a page fault per 4 KiB page when first written (the kernel zeroes it):
    measured here, a ``fill_`` of a 4.9 MB tensor took 12 ms instead of 0.1 ms, and the window
    losses' forward + backward 1.7 s instead of 0.34 s. Serving every block from the heap
    (``M_MMAP_MAX = 0``) and never trimming it (``M_TRIM_THRESHOLD`` at its maximum) keeps the
    freed blocks for the next tensors, which then reuse warm memory. The cost: the process keeps
    its peak heap instead of returning it to the system. Linux/glibc only; a no-op (False)
    elsewhere; idempotent.
    """
    global _ALLOCATOR_TUNED
    if _ALLOCATOR_TUNED:
        return True
    import ctypes
    import ctypes.util
    import sys

    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        M_TRIM_THRESHOLD, M_MMAP_MAX = -1, -4
        ok = libc.mallopt(M_MMAP_MAX, 0) == 1  # no mmap: every block from the (reused) heap
        ok = ok and libc.mallopt(M_TRIM_THRESHOLD, 2**31 - 1) == 1  # int: the largest accepted
    except (OSError, AttributeError):
        return False
    _ALLOCATOR_TUNED = ok
    return ok

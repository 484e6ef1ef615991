"""The roll-out's fast path: one fused mesh-convolution layer with a hand-written backward.

What it fuses, and why. A mesh-conv layer on channel-major frames ``x`` ``(C, V, B)`` is
``y = act(W_s x + A (W_r x) + b) [+ r]`` (``W_s``/``W_r`` the self and ring 9 x 9 channel maps,
``A`` the ring-mean operator, ``act`` tanh or none, ``r`` an optional residual:
the decoder's last layer adds the current frame, ``X_t+1 = X_t + dX``). Written as plain torch
ops with autograd (``MeshConv.forward``, the readable reference), one layer costs about ten
full-size passes in the forward pass and more in the backward: the two maps are one matmul
whose halves are sliced (the backward of each slice allocates and zero-fills a ``(2C, V*B)``
tensor: 24% of an iteration), a bias concatenation, a separate add, an out-of-place tanh; and
every fresh large tensor costs page faults on CPU. ``MeshConvFused`` does the layer in four
passes: ``y = b + W_s x`` (addmm), ``z = W_r x`` (mm), ``y += A z`` (``ring_mean``, one
``embedding_bag``, added in place), activation in place; it saves only ``x`` and the activation's output, and its backward forms
``g`` (the activation's backward), ``A^T g`` once, the input gradient with one mm + one addmm
and the two weight gradients with two small mms.

tanh on CPU: ``torch.tanh`` in this torch build runs at about 2.5 ns per float32 element (six
times slower than ``torch.sigmoid``), so on CPU the layer computes ``tanh(u) = 2 sigmoid(2u) - 1``
with the factor 2 folded into the (9 x 9) weights and bias: the same function to float32
rounding (absolute error ~1e-7). CUDA uses ``torch.tanh``.

Everything here is plain torch operators, so the same code runs on CUDA; nothing is specific to
one device. ``MeshConv.forward`` stays the reference the tests compare this against.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def ring_mean(ring, z: torch.Tensor, transpose: bool = False) -> torch.Tensor:
    """The 1-ring mean (or its transpose) of channel-major ``z`` ``(c, V, B)``, vertex-major out ``(V, c, B)``.

    One ``embedding_bag`` (weighted sum of table rows) over the ``(V, c*B)`` vertex-major table:
    each neighbour entry reads one contiguous row of ``c*B`` floats. Measured 0.33 ms for
    ``(9, 8431, 16)`` against 3.0 ms for the CSR ``(9V, 9V) @ (9V, 16)`` product (torch's CSR
    kernel handles 16-wide rows poorly); the two layout copies around it cost about 1 ms.
    ``ring``: a ``NeighborMean(impl="sparse")`` (its ``bag*`` buffers).
    """
    c, V, B = z.shape
    table = z.permute(1, 0, 2).reshape(V, c * B)
    name = "bag_t" if transpose else "bag"
    out = F.embedding_bag(getattr(ring, f"{name}_index"), table, getattr(ring, f"{name}_offsets"),
                          mode="sum", per_sample_weights=getattr(ring, f"{name}_weight"))
    return out.view(V, c, B)


def fast_tanh_(y: torch.Tensor, prescaled: bool) -> torch.Tensor:
    """tanh in place; ``prescaled``: ``y`` already holds ``2u`` (CPU path, see the module docstring)."""
    if prescaled:
        return y.sigmoid_().mul_(2.0).sub_(1.0)
    return y.tanh_()


class MeshConvFused(torch.autograd.Function):
    """``y = act(W_s x + A (W_r x) + b) [+ residual]`` on ``(C_in, V, B)`` -> ``(C_out, V, B)``.

    ``ring``: the ``NeighborMean(impl="sparse")`` whose operator the layer applies (``ring_mean``).
    ``w_self``, ``w_ring``: ``(C_out, C_in)``; ``bias``: ``(C_out,)``; ``act``: apply tanh.
    """

    @staticmethod
    @torch.autocast("cpu", enabled=False)
    @torch.autocast("cuda", enabled=False)
    def forward(ctx, x, w_self, w_ring, bias, ring, act: bool, residual):
        """Always float32 (memory-bound: bfloat16 would save little and lose precision)."""
        if act and residual is not None:
            raise ValueError("MeshConvFused: a residual after tanh is not supported")
        C_in, V, B = x.shape
        c = w_self.shape[0]
        x2 = x.reshape(C_in, V * B)
        prescaled = act and x.device.type == "cpu"
        s = 2.0 if prescaled else 1.0
        ws, wr, b = (w_self * s, w_ring * s, bias * s) if prescaled else (w_self, w_ring, bias)
        z = torch.mm(wr, x2).view(c, V, B)
        y = torch.addmm(b[:, None], ws, x2)
        y.view(c, V, B).add_(ring_mean(ring, z).permute(1, 0, 2))  # += ring mean of W_r x
        del z
        if act:
            fast_tanh_(y, prescaled)
        if residual is not None:
            y.add_(residual.reshape(c, V * B))
        ctx.ring = ring
        ctx.act, ctx.has_residual, ctx.shape = act, residual is not None, (C_in, V, B)
        ctx.save_for_backward(x2, w_self, w_ring, y if act else None)
        return y.view(c, V, B)

    @staticmethod
    def backward(ctx, gy):
        x2, w_self, w_ring, y = ctx.saved_tensors
        C_in, V, B = ctx.shape
        c = w_self.shape[0]
        gy = gy.reshape(c, V * B)
        g = torch.ops.aten.tanh_backward(gy, y) if ctx.act else gy
        gr = ring_mean(ctx.ring, g.view(c, V, B), transpose=True).permute(1, 0, 2).reshape(c, V * B)  # dL/dz
        gx = torch.mm(w_self.t(), g).addmm_(w_ring.t(), gr)
        gws = torch.mm(g, x2.t())
        gwr = torch.mm(gr, x2.t())
        gb = g.sum(1)
        gres = gy.view(c, V, B) if ctx.has_residual else None
        return gx.view(C_in, V, B), gws, gwr, gb, None, None, gres


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

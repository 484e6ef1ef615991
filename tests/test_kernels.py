"""The fused mesh-conv layer (meshseq.kernels): C++ CPU kernel and torch-op path against plain autograd."""

from __future__ import annotations

import pytest
import torch

from meshseq import kernels
from meshseq.data.synthetic import twisting_limb
from meshseq.kernels import MeshConvFused, MeshConvStack
from meshseq.mesh import Topology
from meshseq.model import NeighborMean


@pytest.fixture(scope="module")
def ring():
    seq = twisting_limb(frames=2, rings=10, segments=7)
    return NeighborMean(Topology.from_faces(seq.faces, seq.n_vertices))


@pytest.fixture(scope="module")
def big_ring():
    """Enough vertices (2880) that each of the kernel's 64 vertex chunks spans several 16-vertex blocks."""
    seq = twisting_limb(frames=2, rings=60, segments=48)
    return NeighborMean(Topology.from_faces(seq.faces, seq.n_vertices))


def plain_layer(x, ws, wr, b, ring, act, residual):
    """``act(W_s x + A (W_r x) + b) [+ r]`` with a dense ``A``, plain autograd, ``x`` ``(V, C, B)``."""
    A = ring.A.to_dense()
    y = torch.einsum("oc,vcb->vob", ws, x) + torch.einsum("uv,vob->uob", A, torch.einsum("oc,vcb->vob", wr, x))
    y = y + b.unsqueeze(-1)  # b (C_out,), or (V, C_out): one per vertex
    if act:
        y = torch.tanh(y)
    return y if residual is None else y + residual


def layer_and_grads(fn, x, ws, wr, b, ring, act, residual, gy):
    leaves = [t.detach().clone().requires_grad_() for t in (x, ws, wr, b)]
    res = None if residual is None else residual.detach().clone().requires_grad_()
    y = fn(*leaves, ring, act, res)
    grads = torch.autograd.grad(y, leaves + ([res] if res is not None else []), gy)
    return y.detach(), grads


def test_the_cpu_kernels_build_here():
    """CI's machine has a C++ compiler: the fast path must really be the C++ one there."""
    assert kernels.cpu_kernels_available()


@pytest.mark.parametrize("windows", [3, 8, 9, 16, 32, 37])  # 8-wide (partial, full), 16-wide (partial, full, two, two + partial)
@pytest.mark.parametrize("act,residual", [(True, False), (False, True), (False, False)])
@pytest.mark.parametrize("path", ["cpp", "torch"])
def test_fused_layer_matches_plain_autograd(ring, windows, act, residual, path, monkeypatch):
    if path == "torch":
        monkeypatch.setattr(kernels, "_cpu_kernels", False)
    else:
        assert kernels.cpu_kernels_available()
    torch.manual_seed(windows)
    V, C = ring.n_vertices, 9
    x = torch.randn(V, C, windows)
    ws, wr, b = 0.4 * torch.randn(C, C), 0.4 * torch.randn(C, C), torch.randn(C)
    r = torch.randn(V, C, windows) if residual else None
    gy = torch.randn(V, C, windows)
    y, grads = layer_and_grads(MeshConvFused.apply, x, ws, wr, b, ring, act, r, gy)
    y_ref, grads_ref = layer_and_grads(plain_layer, x, ws, wr, b, ring, act, r, gy)
    torch.testing.assert_close(y, y_ref, atol=2e-6, rtol=1e-5)
    assert len(grads) == len(grads_ref)
    for name, g, g_ref in zip(["x", "w_self", "w_ring", "bias", "residual"], grads, grads_ref):
        err = float((g - g_ref).norm() / g_ref.norm())
        assert err <= 1e-5, f"{path} {name}: relative error {err:.2e}"


# (9, 9): the channel counts the kernel knows at compile time (ACAP's); others at run time
@pytest.mark.parametrize("c_in,c_out", [(9, 9), (4, 6), (7, 5)])
@pytest.mark.parametrize("windows", [8, 16, 19])
@pytest.mark.parametrize("act", [True, False])
def test_cpu_kernel_matches_plain_autograd_for_any_channels_on_a_larger_mesh(big_ring, c_in, c_out, windows, act):
    assert kernels.cpu_kernels_available()
    assert big_ring.n_vertices > 64 * 16 * 2
    torch.manual_seed(c_in + windows)
    V = big_ring.n_vertices
    x, gy = torch.randn(V, c_in, windows), torch.randn(V, c_out, windows)
    ws, wr, b = 0.4 * torch.randn(c_out, c_in), 0.4 * torch.randn(c_out, c_in), torch.randn(c_out)
    r = None if act else torch.randn(V, c_out, windows)
    y, grads = layer_and_grads(MeshConvFused.apply, x, ws, wr, b, big_ring, act, r, gy)
    y_ref, grads_ref = layer_and_grads(plain_layer, x, ws, wr, b, big_ring, act, r, gy)
    torch.testing.assert_close(y, y_ref, atol=2e-6, rtol=1e-5)
    for name, g, g_ref in zip(["x", "w_self", "w_ring", "bias", "residual"], grads, grads_ref):
        err = float((g - g_ref).norm() / g_ref.norm())
        assert err <= 1e-5, f"{name}: relative error {err:.2e}"


# the encoder's stack (tanh after each layer) and the decoder's (tanh, tanh, linear + residual)
@pytest.mark.parametrize("acts,residual", [((True, True, True), False), ((True, True, False), True),
                                           ((False, True), False), ((True,), False)])
@pytest.mark.parametrize("path", ["cpp", "torch"])
# the first layer's bias one per vertex (V, C_out): the encoder's input normalisation folded in
@pytest.mark.parametrize("vertex_bias", [False, True])
def test_conv_stack_matches_plain_autograd_layer_by_layer(big_ring, acts, residual, path, vertex_bias, monkeypatch):
    """MeshConvStack's backward hands the layers below the top their pre-activation gradients
    (the input gradient times 1 - x^2 written by the layer above): the same gradients as plain
    autograd through the layers one by one."""
    if path == "torch":
        monkeypatch.setattr(kernels, "_cpu_kernels", False)
    else:
        assert kernels.cpu_kernels_available()
    torch.manual_seed(len(acts) + residual)
    V, C, B = big_ring.n_vertices, 9, 16
    x, gy = torch.randn(V, C, B), torch.randn(V, C, B)
    r = torch.randn(V, C, B) if residual else None
    params = [t for _ in acts for t in (0.4 * torch.randn(C, C), 0.4 * torch.randn(C, C), torch.randn(C))]
    if vertex_bias:
        params[2] = torch.randn(V, C)

    def run(stack):
        leaves = [t.detach().clone().requires_grad_() for t in [x] + params]
        res = None if r is None else r.detach().clone().requires_grad_()
        if stack:
            y = MeshConvStack.apply(leaves[0], res, big_ring, acts, *leaves[1:])
        else:
            y = leaves[0]
            for k, act in enumerate(acts):
                last = k == len(acts) - 1
                y = plain_layer(y, *leaves[1 + 3 * k: 4 + 3 * k], big_ring, act, res if last else None)
        grads = torch.autograd.grad(y, leaves + ([res] if res is not None else []), gy)
        return y.detach(), grads

    (y, grads), (y_ref, grads_ref) = run(True), run(False)
    torch.testing.assert_close(y, y_ref, atol=2e-6, rtol=1e-5)
    assert len(grads) == len(grads_ref) == 1 + len(params) + residual
    for i, (g, g_ref) in enumerate(zip(grads, grads_ref)):
        err = float((g - g_ref).norm() / g_ref.norm())
        assert err <= 1e-5, f"{path}: gradient {i} relative error {err:.2e}"


@pytest.mark.parametrize("mesh", ["ring", "big_ring"])
def test_cpu_kernel_gradients_have_the_same_bits_with_any_thread_count(mesh, request):
    assert kernels.cpu_kernels_available()
    ring = request.getfixturevalue(mesh)
    torch.manual_seed(0)
    V, C = ring.n_vertices, 9
    x, gy = torch.randn(V, C, 16), torch.randn(V, C, 16)
    ws, wr, b = torch.randn(C, C), torch.randn(C, C), torch.randn(C)
    before = torch.get_num_threads()
    out = []
    try:
        for threads in (1, 3):
            torch.set_num_threads(threads)
            out.append(layer_and_grads(MeshConvFused.apply, x, ws, wr, b, ring, True, None, gy))
    finally:
        torch.set_num_threads(before)
    (y1, g1), (y3, g3) = out
    assert torch.equal(y1, y3)
    assert all(torch.equal(a, c) for a, c in zip(g1, g3))


# N: a whole number of 16-column blocks plus a remainder, and more than one 2048-column chunk of
# fc_wx; L: 8-row blocks plus a remainder; B: 8-wide and 16-wide tiles, one and two of them
@pytest.mark.parametrize("L,N,B", [(16, 4103, 16), (13, 4103, 8), (24, 150, 32), (8, 40, 24)])
@pytest.mark.parametrize("with_bias", [True, False])
def test_fc_products_match_torch(L, N, B, with_bias):
    assert kernels.cpu_kernels_available()
    torch.manual_seed(L + N + B)
    W, x, h = torch.randn(L, N), torch.randn(N, B), torch.randn(L, B)
    assert kernels._use_fc_kernels(W, x) and kernels._use_fc_kernels(W, h)  # the C++ path is what runs
    b_l, b_n = (torch.randn(L), torch.randn(N)) if with_bias else (None, None)
    wx = kernels.fc_product(W, x, b_l)
    wtx = kernels.fc_transposed_product(W, h, b_n)
    ref_wx = (W.double() @ x.double()) + (0 if b_l is None else b_l.double()[:, None])
    ref_wtx = (W.double().t() @ h.double()) + (0 if b_n is None else b_n.double()[:, None])
    assert wx.shape == (L, B) and wtx.shape == (N, B)
    for got, ref in ((wx, ref_wx), (wtx, ref_wtx)):  # float32 rounding of sums of N terms
        assert float((got.double() - ref).abs().max() / ref.abs().max()) <= 4e-6
    if not with_bias:  # the decoder backward's product with x's row sums (its bias gradient)
        wx2, sums = kernels.fc_product_and_row_sums(W, x)
        assert torch.equal(wx2, wx) and sums.shape == (N,)
        torch.testing.assert_close(sums, x.sum(1), rtol=1e-5, atol=1e-5)


def test_fc_products_fall_back_to_torch_for_other_shapes_and_dtypes():
    W, x = torch.randn(8, 40), torch.randn(40, 6)  # 6 columns: not a multiple of 8
    assert not kernels._use_fc_kernels(W, x)
    torch.testing.assert_close(kernels.fc_product(W, x), W @ x)
    Wb = W.to(torch.bfloat16)  # --precision bf16: the product in the weight's dtype
    assert kernels.fc_product(Wb, torch.randn(40, 8)).dtype == torch.bfloat16


def test_fc_products_have_the_same_bits_with_any_thread_count():
    torch.manual_seed(0)
    W, x, h = torch.randn(16, 5000), torch.randn(5000, 16), torch.randn(16, 16)
    before = torch.get_num_threads()
    out = []
    try:
        for threads in (1, 3):
            torch.set_num_threads(threads)
            out.append((kernels.fc_product(W, x), kernels.fc_transposed_product(W, h)))
    finally:
        torch.set_num_threads(before)
    assert torch.equal(out[0][0], out[1][0]) and torch.equal(out[0][1], out[1][1])


# every L the kernel has; N: whole register tiles of rows plus a remainder; pairs of unequal widths
@pytest.mark.parametrize("L,N", [(16, 4103), (32, 301), (64, 1000), (128, 4102), (256, 97)])
def test_fc_weight_gradient_matches_the_sum_of_products(L, N):
    assert kernels.cpu_kernels_available()
    torch.manual_seed(L + N)
    widths = [16, 6, 16, 3]
    rights = [torch.randn(N, b) for b in widths]
    lefts = [torch.randn(b, L) for b in widths]
    left = torch.cat(lefts)
    assert kernels.fc_weight_gradient_supported(left, rights), "no fc_weight_grad kernel for this L"
    g = kernels.fc_weight_gradient(left, rights)
    ref = sum(lt.double().t() @ r.double().t() for lt, r in zip(lefts, rights))
    assert g.shape == (L, N) and g.dtype == torch.float32
    assert float((g.double() - ref).abs().max() / ref.abs().max()) <= 4e-6
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = kernels.fc_weight_gradient(left, rights)
        torch.set_num_threads(3)
        three = kernels.fc_weight_gradient(left, rights)
    finally:
        torch.set_num_threads(before)
    assert torch.equal(one, g) and torch.equal(three, g)  # the same bits with any thread count


def test_fc_weight_gradient_is_left_to_torch_for_other_latent_sizes_and_dtypes():
    rights = [torch.randn(50, 8)]
    assert not kernels.fc_weight_gradient_supported(torch.randn(8, 24), rights)  # L = 24: no kernel
    assert not kernels.fc_weight_gradient_supported(torch.randn(8, 128, dtype=torch.bfloat16), rights)


# the roll-out's size; a batch that is not a whole register tile of rows, a width that is not a
# whole tile of columns (48 = 3 vectors of 16), one layer
@pytest.mark.parametrize("H,B,K", [(128, 16, 3), (16, 6, 2), (48, 5, 1)])
def test_lstm_step_kernel_matches_torch_lstm_cell(H, B, K):
    from torch import nn

    from meshseq.model import lstm_step

    assert kernels.cpu_kernels_available()
    torch.manual_seed(H + B + K)
    lstm = nn.LSTM(H, H, K)
    z, h, c = torch.randn(B, H), torch.randn(K, B, H), torch.randn(K, B, H)
    grads_out = (torch.randn(B, H), torch.randn(K, B, H), torch.randn(K, B, H))
    assert kernels.lstm_step_supported(lstm, z)  # the C++ path is what runs

    def run(transposed):
        inputs = [t.clone().requires_grad_() for t in (z, h, c)]
        out, (h2, c2) = lstm_step(lstm, *inputs, transposed=transposed)
        grads = torch.autograd.grad([out, h2, c2], [*inputs, *lstm.parameters()], grads_out)
        return [t.detach() for t in (out, h2, c2, *grads)]

    ref, fast = run(None), run(kernels.lstm_transposed(lstm))
    for a, b in zip(fast, ref):  # outputs, input and state gradients, every weight's and bias's gradient
        assert a.shape == b.shape
        assert float((a - b).norm() / b.norm()) <= 2e-6
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = run(kernels.lstm_transposed(lstm))
        torch.set_num_threads(3)
        three = run(kernels.lstm_transposed(lstm))
    finally:
        torch.set_num_threads(before)
    assert all(torch.equal(a, b) and torch.equal(a, f) for a, b, f in zip(one, three, fast))  # same bits


def test_lstm_step_is_left_to_torch_for_other_widths_dtypes_and_autocast():
    from torch import nn

    lstm = nn.LSTM(24, 24, 1)  # not a multiple of 16
    assert not kernels.lstm_step_supported(lstm, torch.randn(3, 24))
    lstm = nn.LSTM(16, 16, 1)
    assert kernels.lstm_step_supported(lstm, torch.randn(3, 16))
    assert not kernels.lstm_step_supported(lstm.double(), torch.randn(3, 16, dtype=torch.float64))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert not kernels.lstm_step_supported(lstm.float(), torch.randn(3, 16))


@pytest.mark.parametrize("steps", [False, True])
@pytest.mark.parametrize("both", [True, False])
@pytest.mark.parametrize("values", [9 * 7, 9 * 300])  # a partial chunk; more than one chunk
@pytest.mark.parametrize("B", [3, 9])  # lanes one at a time; a group of 8 lanes and one more
def test_frame_errors_match_torch_and_plain_autograd(both, values, steps, B, monkeypatch):
    assert kernels.cpu_kernels_available()
    torch.manual_seed(values + B)
    n = 5
    windows = torch.randn(B, n, values // 9, 9)
    chains = torch.randn(2 * B if both else B, n, values // 9, 9)
    ge = torch.randn(6 if steps else 3, B, n)

    def run():
        c = chains.clone().requires_grad_()
        e = kernels.frame_errors(c, windows, steps=steps)
        (gc,) = torch.autograd.grad(e, c, ge)
        return e.detach(), gc

    e_cpp, g_cpp = run()
    monkeypatch.setattr(kernels, "_cpu_kernels", False)  # the torch-operator path
    e_ref, g_ref = run()
    # by hand: window 1, frame 1 of each row
    f, x = chains[1, 1], windows[1, 1]
    assert float(e_cpp[0, 1, 1]) == pytest.approx(float((f - x).square().sum()), rel=1e-5)
    if both:
        g = chains[B + 1, n - 2]  # the backward chain's frame n-2 pairs with x_1
        assert float(e_cpp[1, 1, n - 2]) == pytest.approx(float((g - x).square().sum()), rel=1e-5)
        assert float(e_cpp[2, 1, 1]) == pytest.approx(float((f - g).square().sum()), rel=1e-5)
    else:
        assert e_cpp[1:3].abs().max() == 0
    if steps:
        assert e_cpp.shape == (6, B, n) and e_cpp[3:, :, 0].abs().max() == 0
        assert float(e_cpp[3, 1, 1]) == pytest.approx(float((f - chains[1, 0]).square().sum()), rel=1e-5)
        assert float(e_cpp[5, 1, 1]) == pytest.approx(float((x - windows[1, 0]).square().sum()), rel=1e-5)
        if both:
            assert float(e_cpp[4, 1, 2]) == pytest.approx(float((chains[B + 1, 2] - chains[B + 1, 1]).square().sum()),
                                                          rel=1e-5)
        else:
            assert e_cpp[4].abs().max() == 0
    torch.testing.assert_close(e_cpp, e_ref, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(g_cpp, g_ref, rtol=1e-5, atol=1e-5)


def test_frame_errors_of_vertex_major_frames_match_the_stacked_chains_and_skip_frames_without_gradient():
    assert kernels.cpu_kernels_available()
    torch.manual_seed(1)
    B, n, V = 8, 6, 40
    windows = torch.randn(B, n, V, 9)
    frames = [torch.randn(V, 9, 2 * B, requires_grad=i > 0) for i in range(n)]  # frame 0: given, no gradient
    ge = torch.randn(6, B, n)
    e = kernels.frame_errors_of_frames(frames, windows, steps=True)
    grads = torch.autograd.grad(e, frames[1:], ge)
    chains = torch.stack([f.detach().permute(2, 0, 1) for f in frames], 1).requires_grad_()
    e_ref = kernels._frame_errors_torch(chains, windows, steps=True)
    (g_ref,) = torch.autograd.grad(e_ref, chains, ge)
    torch.testing.assert_close(e, e_ref, rtol=1e-5, atol=1e-5)
    for i, g in enumerate(grads, start=1):
        assert g.shape == (V, 9, 2 * B) and g.is_contiguous()
        torch.testing.assert_close(g, g_ref[:, i].permute(1, 2, 0), rtol=1e-5, atol=1e-5)
    # a frame that needs no gradient gets none
    e2 = kernels.frame_errors_of_frames(frames, windows)
    e2.sum().backward()
    assert frames[0].grad is None and frames[1].grad is not None


def test_frame_errors_have_the_same_bits_with_any_thread_count():
    torch.manual_seed(0)
    windows, chains, ge = torch.randn(2, 4, 500, 9), torch.randn(4, 4, 500, 9), torch.randn(6, 2, 4)
    before = torch.get_num_threads()
    out = []
    try:
        for threads in (1, 3):
            torch.set_num_threads(threads)
            c = chains.clone().requires_grad_()
            e = kernels.frame_errors(c, windows, steps=True)
            out.append((e.detach(), torch.autograd.grad(e, c, ge)[0]))
    finally:
        torch.set_num_threads(before)
    assert torch.equal(out[0][0], out[1][0]) and torch.equal(out[0][1], out[1][1])


def test_each_kind_of_cpu_gets_its_own_build():
    """-march=native builds must not be shared between CPUs with different instruction sets."""
    avx2 = "processor\t: 0\nflags\t\t: fpu sse2 avx avx2 fma\nprocessor\t: 1\nflags\t\t: fpu sse2 avx avx2 fma\n"
    avx512 = "processor\t: 0\nflags\t\t: fpu sse2 avx avx2 fma avx512f avx512bw\n"
    a, b = kernels.cpu_signature(avx2), kernels.cpu_signature(avx512)
    assert a != b and len(a) == len(b) == 8
    assert kernels.cpu_signature(avx2.replace("avx avx2", "avx2 avx")) == a  # the set, not the order
    assert kernels.cpu_signature() == kernels.cpu_signature()  # this machine: stable


def test_a_stale_build_lock_is_removed_and_a_fresh_one_kept(tmp_path):
    """A killed build leaves build/lock, and torch's builder would wait for it forever."""
    import os
    import time

    lock = tmp_path / "lock"
    lock.write_text("")
    assert not kernels.clear_stale_lock(tmp_path) and lock.exists()  # a build may be running now
    old = time.time() - 3600
    os.utime(lock, (old, old))
    with pytest.warns(RuntimeWarning, match="stale build lock"):
        assert kernels.clear_stale_lock(tmp_path)
    assert not lock.exists()
    assert not kernels.clear_stale_lock(tmp_path)  # nothing there: nothing to do


def test_waiting_for_a_build_lock_ends_when_it_goes_or_turns_stale(tmp_path):
    import os
    import threading
    import time
    import warnings

    from meshseq import kernels

    assert kernels.wait_for_build_lock(tmp_path, poll_s=0.01) < 0.5  # no lock: no wait
    lock = tmp_path / "lock"
    lock.touch()
    threading.Timer(0.3, lock.unlink).start()  # another process's build ends
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        waited = kernels.wait_for_build_lock(tmp_path, poll_s=0.01)
    assert 0.25 < waited < 5 and any("waiting for another process" in str(w.message) for w in caught)
    lock.touch()
    old = time.time() - 3600
    os.utime(lock, (old, old))  # a killed build's lock
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert kernels.wait_for_build_lock(tmp_path, poll_s=0.01) < 0.5
    assert not lock.exists()

"""The BD-LSTM generator: mesh convolution, tied encoder/decoder, chains and variants."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from meshseq import kernels
from meshseq.data.synthetic import twisting_limb
from meshseq.errors import MeshseqError
from meshseq.mesh import Topology
from meshseq.model import BDLSTM, MeshConv, ModelConfig, NeighborMean, count_step_flops, lstm_step


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def limb():
    seq = twisting_limb(frames=6, rings=8, segments=6)
    return Topology.from_faces(seq.faces, seq.n_vertices)


def make(topo, variant="bd", conv="sparse", latent=16, layers=2, seed=0, input_norm=False):
    torch.manual_seed(seed)
    cfg = ModelConfig(n_vertices=topo.n_vertices, latent=latent, lstm_layers=layers, variant=variant, conv_impl=conv,
                      input_norm=input_norm)
    return BDLSTM(cfg, topo)


def ring_mean_reference(x: np.ndarray, topo: Topology) -> np.ndarray:
    """Brute-force 1-ring mean of vertex-major ``(V, ...)`` from the adjacency lists."""
    return np.stack([x[list(r)].mean(0) for r in topo.adjacency.tolil().rows])


@pytest.mark.parametrize("impl", ["sparse", "gather"])
def test_neighbor_mean_matches_brute_force_and_gradients_agree(limb, impl):
    x = torch.randn(limb.n_vertices, 5, 3, dtype=torch.float32, requires_grad=True)  # (V, C, B)
    ring = NeighborMean(limb, impl)
    y = ring(x)
    np.testing.assert_allclose(y.detach().numpy(), ring_mean_reference(x.detach().numpy(), limb), atol=1e-6)
    # backward = transpose of the mean operator: <A x, g> = <x, A^T g>
    g = torch.randn_like(y)
    (gx,) = torch.autograd.grad(y, x, g)
    adj = limb.adjacency.toarray()
    A = torch.from_numpy(adj / adj.sum(1, keepdims=True)).float()
    torch.testing.assert_close(gx, torch.einsum("vw,vcb->wcb", A, g), atol=1e-5, rtol=1e-5)


def test_mesh_conv_is_paper_eq2(limb):
    ring = NeighborMean(limb, "sparse")
    conv = MeshConv(9, 9, ring)
    x = torch.randn(limb.n_vertices, 9, 2)  # vertex-major (V, C, B)
    W1, W2 = conv.weight[:9].detach(), conv.weight[9:].detach()
    ring_x = torch.from_numpy(ring_mean_reference(x.numpy(), limb)).float()
    with torch.no_grad():
        conv.bias.uniform_()
        # per vertex: y_i = W1^T x_i + W2^T mean_ring(x)_i + b (the paper's Eq. 2, column vectors)
        xr, rr = x.permute(0, 2, 1), ring_x.permute(0, 2, 1)  # (V, B, C) rows
        expected = (xr @ W1 + rr @ W2 + conv.bias).permute(0, 2, 1)
        torch.testing.assert_close(conv(x), expected, atol=1e-5, rtol=1e-5)
        b = torch.randn(9)
        expected = (xr @ W1.t() + rr @ W2.t() + b).permute(0, 2, 1)
        torch.testing.assert_close(conv(x, transpose=True, bias=b), expected, atol=1e-5, rtol=1e-5)


def test_fc_weight_gradient_summed_over_time_equals_plain_autograd(limb):
    """The one-matmul FC weight gradient of a roll-out equals step-by-step autograd."""
    m = make(limb)
    w = torch.randn(2, 5, limb.n_vertices, 9) * 0.1

    def grads(deferred):
        m.zero_grad()
        fc = m._fc_ops(deferred=deferred)
        x = w[:, 0].permute(1, 2, 0).contiguous()
        state = m.initial_state(2)
        total = 0
        for t in range(1, 5):
            state, x, mu, _ = m._step_vm(state, x, fc, False, None)
            total = total + (x - w[:, t].permute(1, 2, 0)).square().sum() + mu.square().sum()
        (total + m.fc.weight.square().sum()).backward()
        return {n: p.grad.clone() for n, p in m.named_parameters() if p.grad is not None}

    plain, deferred = grads(False), grads(True)
    assert plain.keys() == deferred.keys() and "fc.weight" in plain
    for n in plain:
        torch.testing.assert_close(deferred[n], plain[n], atol=1e-5, rtol=1e-4, msg=n)
    assert plain["fc.weight"].abs().sum() > 0


def test_shapes_of_every_variant(limb):
    V = limb.n_vertices
    for variant in ("bd", "std-bd", "uni"):
        m = make(limb, variant)
        w = torch.randn(3, 5, V, 9) * 0.1
        out = m(w)
        assert out["forward"].shape == (3, 5, V, 9)
        torch.testing.assert_close(out["forward"][:, 0], w[:, 0])
        rows = 3 if variant == "uni" else 6
        assert out["mu"].shape == out["logvar"].shape == (4, rows, 16)
        if variant == "uni":
            assert out["backward"] is None
        else:
            assert out["backward"].shape == (3, 5, V, 9)
            torch.testing.assert_close(out["backward"][:, 0], w[:, -1])  # backward chain starts at X_n
        mu, logvar = m.encode(w[:, 0])
        assert mu.shape == (3, 16) and logvar.shape == (3, 16)
        assert m.decode(mu).shape == (3, V, 9)


def test_rollout_output_stacks_on_demand_and_picks_frames_with_their_gradients(limb):
    V = limb.n_vertices
    m = make(limb, "bd")
    w = torch.randn(3, 5, V, 9) * 0.1
    torch.manual_seed(0)
    out = m(w, sample=False)
    assert set(out) == {"frames", "mu", "logvar"}  # nothing stacked yet
    assert len(out["frames"]) == 5 and out["frames"][2].shape == (V, 9, 6)
    torch.manual_seed(0)
    ref = m(w, sample=False)
    picks = [1, 4]
    picked = out.frames_at(picks)
    torch.testing.assert_close(picked, ref["chains"][:, picks])
    torch.testing.assert_close(ref["forward"], ref["chains"][:3])
    torch.testing.assert_close(ref["backward"], ref["chains"][3:])
    weights = torch.randn_like(picked)
    params = [p for p in m.parameters() if p.requires_grad]
    got = torch.autograd.grad((picked * weights).sum(), params, allow_unused=True)
    want = torch.autograd.grad((ref["chains"][:, picks] * weights).sum(), params, allow_unused=True)
    for a, b in zip(got, want):
        assert (a is None) == (b is None)
        if a is not None:
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def test_step_is_x_plus_decoded_lstm_output(limb):
    m = make(limb)
    x = torch.randn(2, limb.n_vertices, 9) * 0.1
    state = m.initial_state(2)
    new_state, nxt, mu, _ = m.step(state, x)  # evaluation: z = mu
    out, (h, c) = m.lstm(mu.unsqueeze(0), state)
    torch.testing.assert_close(nxt, x + m.decode(out[0]))
    torch.testing.assert_close(new_state[0], h)
    torch.testing.assert_close(new_state[1], c)


def test_initial_states_are_plus_and_minus_point_one(limb):
    m = make(limb)
    h, c = m.initial_state(2, 3)
    assert h.shape == c.shape == (2, 5, 16)
    assert torch.all(h[:, :2] == 0.1) and torch.all(c[:, :2] == 0.1)
    assert torch.all(h[:, 2:] == -0.1) and torch.all(c[:, 2:] == -0.1)


def test_decoder_is_tied_to_encoder(limb):
    m = make(limb)
    names = dict(m.named_parameters())
    V, L = limb.n_vertices, 16
    big = [n for n, p in names.items() if p.numel() >= V * 9 * L]
    assert big == ["fc.weight"]  # one big FC matrix, no decoder copy
    h = torch.randn(2, L)
    before = m.decode(h).detach().clone()
    with torch.no_grad():
        m.fc.weight.add_(0.01 * torch.randn_like(m.fc.weight))
    assert not torch.allclose(m.decode(h), before)
    # the decoder convolutions are the encoder's weights, in reverse order
    with torch.no_grad():
        m.decode(h)
        before = m.decode(h).clone()
        m.convs[-1].weight.mul_(1.5)
        after_last = m.decode(h).clone()
    assert not torch.allclose(before, after_last)
    # gradients of the decoder reach the encoder's weights
    m.zero_grad()
    m.decode(h).square().sum().backward()
    assert m.fc.weight.grad is not None and m.fc.weight.grad.abs().sum() > 0
    assert all(c.weight.grad.abs().sum() > 0 for c in m.convs)
    assert all(b.grad is not None for b in m.dec_conv_bias)


def test_shared_variant_has_one_parameter_set_and_batches_both_chains(limb):
    bd, std = make(limb, "bd"), make(limb, "std-bd")
    assert bd.lstm_backward is None
    n_bd = sum(p.numel() for p in bd.parameters())
    n_std = sum(p.numel() for p in std.parameters())
    assert n_std - n_bd == sum(p.numel() for p in std.lstm_backward.parameters()) > 0
    w = torch.randn(2, 4, limb.n_vertices, 9) * 0.1
    out = bd(w, sample=False)
    # the backward chain is the same generator run on the reversed window from -0.1
    frames, _, _, _ = bd.rollout(w.flip(1)[:, 0], 3, bd.initial_state(0, 2), n_forward=0)
    torch.testing.assert_close(out["backward"], frames, atol=1e-6, rtol=1e-6)
    frames_f, _, _, _ = bd.rollout(w[:, 0], 3, bd.initial_state(2, 0))
    torch.testing.assert_close(out["forward"], frames_f, atol=1e-6, rtol=1e-6)
    # std-bd: the backward chain uses its own LSTM
    out_std = std(w, sample=False)
    frames_wrong, _, _, _ = std.rollout(w.flip(1)[:, 0], 3, std.initial_state(0, 2), n_forward=2)
    frames_right, _, _, _ = std.rollout(w.flip(1)[:, 0], 3, std.initial_state(0, 2), n_forward=0)
    torch.testing.assert_close(out_std["backward"], frames_right, atol=1e-6, rtol=1e-6)
    assert not torch.allclose(out_std["backward"][:, 1:], frames_wrong[:, 1:])


def test_gather_and_sparse_models_agree(limb):
    a, b = make(limb, conv="sparse"), make(limb, conv="gather")
    b.load_state_dict(a.state_dict())
    w = torch.randn(2, 4, limb.n_vertices, 9) * 0.1
    torch.testing.assert_close(a(w, sample=False)["forward"], b(w, sample=False)["forward"], atol=1e-5, rtol=1e-5)


def test_sampling_noise_only_in_training_mode(limb):
    m = make(limb)
    w = torch.randn(2, 4, limb.n_vertices, 9) * 0.1
    torch.testing.assert_close(m(w, sample=False)["forward"], m(w, sample=False)["forward"])
    assert not torch.equal(m(w, sample=True)["forward"], m(w, sample=True)["forward"])


def test_bad_config_is_a_meshseq_error(limb):
    with pytest.raises(MeshseqError, match="variant"):
        ModelConfig(n_vertices=10, variant="bidirectional")
    with pytest.raises(MeshseqError, match="conv"):
        ModelConfig(n_vertices=10, conv_impl="dense")
    with pytest.raises(MeshseqError, match="vertices"):
        BDLSTM(ModelConfig(n_vertices=limb.n_vertices + 1), limb)


def test_flop_count_formulas(limb):
    cfg = ModelConfig(n_vertices=limb.n_vertices, latent=16, lstm_layers=2)
    f = count_step_flops(cfg, limb, batch=4)
    V, nnz = limb.n_vertices, int(limb.degrees.sum())
    assert f["fc"] == 4 * 2 * (2 * V * 9 * 16)  # encoder FC and its transpose
    assert f["lstm"] == 4 * 2 * (2 * 4 * 16 * 32)  # 2 layers, 4 gates, [x, h] -> 16
    assert f["conv"] == 4 * 3 * 2 * (2 * 2 * V * 81 + 2 * nnz * 9)


def test_encode_decode_match_a_plain_batch_major_reference(limb):
    """The vertex-major internals compute exactly the documented network on (B, V, 9) frames."""
    m = make(limb)
    with torch.no_grad():
        for p in m.parameters():
            p.add_(0.05 * torch.randn_like(p))  # non-zero biases too
    adj = limb.adjacency.toarray()
    A = torch.from_numpy(adj / adj.sum(1, keepdims=True)).float()
    B, V = 3, limb.n_vertices
    x = torch.randn(B, V, 9) * 0.3

    def conv(c, y, transpose, bias):
        W1, W2 = c.weight[:9], c.weight[9:]
        if transpose:
            W1, W2 = W1.t(), W2.t()
        return y @ W1 + torch.einsum("vw,bwc->bvc", A, y) @ W2 + bias

    with torch.no_grad():
        y = x
        for c in m.convs:
            y = torch.tanh(conv(c, y, False, c.bias))
        e = y.reshape(B, V * 9) @ m.fc.weight.t() + m.fc.bias  # vertex-major flattening
        mu, logvar = m.encode(x)
        torch.testing.assert_close(mu, m.fc_mu(e), atol=1e-5, rtol=1e-4)
        torch.testing.assert_close(logvar, m.fc_logvar(e), atol=1e-5, rtol=1e-4)
        h = torch.randn(B, 16)
        y = (h @ m.fc.weight + m.dec_fc_bias).view(B, V, 9)
        for k in range(3):
            y = conv(m.convs[2 - k], y, True, m.dec_conv_bias[k])
            y = torch.tanh(y) if k < 2 else y
        torch.testing.assert_close(m.decode(h), y, atol=1e-5, rtol=1e-4)


def _reference_rollout(m, first, steps, state, n_forward):
    """The plain step-by-step roll-out: ``MeshConv.forward`` per layer, per-step FC autograd."""
    fc = m._fc_ops(deferred=False, fused=False)
    assert not fc.fused
    x = first.permute(1, 2, 0)
    frames, mus, logvars = [x], [], []
    for _ in range(steps):
        state, x, mu, logvar = m._step_vm(state, x, fc, True, n_forward)
        frames.append(x)
        mus.append(mu)
        logvars.append(logvar)
    return torch.stack(frames).permute(3, 0, 1, 2), torch.stack(mus), torch.stack(logvars), state


@pytest.mark.parametrize("windows", [3, 4])  # 6 chains: the FC products by torch; 8: by csrc/fc.cpp
# the FC weight gradient by csrc/fc.cpp's kernel, or by torch in one block of rows, in several
@pytest.mark.parametrize("bank_rows", [None, 4096, 50])
# the default recipe's input normalisation, folded into the fast path's first encoder layer
@pytest.mark.parametrize("input_norm", [False, True])
def test_fast_rollout_matches_plain_step_by_step_reference(limb, monkeypatch, windows, bank_rows, input_norm):
    """Loss and every gradient of the fused roll-out equal the plain reference to 1e-5 relative."""
    from meshseq import model as model_module
    from meshseq.model import _GradBank
    from meshseq.train import TrainConfig, WindowLoss

    if bank_rows is None:  # and the LSTM steps by csrc/lstm.cpp
        assert kernels.cpu_kernels_available(), "the C++ kernels did not build"
        used = []
        kernel, lstm_kernel = model_module.fc_weight_gradient, model_module.LSTMStep.apply
        monkeypatch.setattr(model_module, "fc_weight_gradient", lambda *a: used.append("fc") or kernel(*a))
        monkeypatch.setattr(model_module.LSTMStep, "apply", lambda *a: used.append("lstm") or lstm_kernel(*a))
    else:
        monkeypatch.setattr(model_module, "fc_weight_gradient_supported", lambda left, rights: False)
        monkeypatch.setattr(_GradBank, "ROWS", bank_rows)

    m = make(limb, latent=16, layers=3, input_norm=input_norm)
    with torch.no_grad():
        for p in m.parameters():
            p.add_(0.05 * torch.randn_like(p))  # non-zero biases too
    w = torch.randn(windows, 6, limb.n_vertices, 9) * 0.3
    if input_norm:  # an offset per vertex and channel, a spread per channel, far from 0 and 1
        m.set_input_norm((0.2 * torch.randn(40, limb.n_vertices, 9) + torch.randn(limb.n_vertices, 9)).numpy())
    objective = WindowLoss(m, TrainConfig(w_vertex=0.0))

    def run():
        m.zero_grad()
        torch.manual_seed(1)  # the same sampling noise in both runs
        total, _ = objective(w)
        total.backward()
        return total.detach(), {n: p.grad.clone() for n, p in m.named_parameters()}

    fast_loss, fast = run()
    monkeypatch.setattr(m, "rollout", lambda first, steps, state, sample=False, n_forward=None, feedback_grad=True:
                        _reference_rollout(m, first, steps, state, n_forward))
    ref_loss, ref = run()
    assert abs(float(fast_loss) - float(ref_loss)) <= 1e-5 * abs(float(ref_loss))
    for n in ref:
        err = (fast[n] - ref[n]).norm() / ref[n].norm()
        assert err <= 1e-5, f"{n}: relative error {float(err):.2e}"
    if bank_rows is None:
        assert "fc" in used, "the fast roll-out did not form the FC weight gradient with the C++ kernel"
        assert "lstm" in used, "the fast roll-out did not run its LSTM steps with the C++ kernel"


def _reference_rollout_fed_back_as_constants(m, first, steps, state, n_forward):
    """The plain step-by-step roll-out, each generated frame detached before the encoder reads it."""
    fc = m._fc_ops(deferred=False, fused=False)
    x = first.permute(1, 2, 0)
    frames, mus, logvars = [x], [], []
    for _ in range(steps):
        mu, logvar = m._encode_vm(x.detach(), fc)
        z = mu + torch.exp(0.5 * logvar) * torch.randn_like(mu)
        h, state = m._lstm(z, state, n_forward)
        x = m._decode_vm(h, fc, residual=x)
        frames.append(x)
        mus.append(mu)
        logvars.append(logvar)
    return torch.stack(frames).permute(3, 0, 1, 2), torch.stack(mus), torch.stack(logvars), state


def test_feedback_grad_stop_treats_fed_back_frames_as_constants(limb, monkeypatch):
    """``feedback_grad="stop"``: the same loss as "full", the gradients of a roll-out whose encoder
    reads detached frames (to 1e-5 relative); the frames then depend on the first one only through
    the residual path (with "full" also through the encoder)."""
    from meshseq.train import TrainConfig, WindowLoss

    m = make(limb, latent=16, layers=3)
    with torch.no_grad():
        for p in m.parameters():
            p.add_(0.05 * torch.randn_like(p))
    w = torch.randn(3, 6, limb.n_vertices, 9) * 0.3

    def run(feedback_grad):
        m.zero_grad()
        torch.manual_seed(1)
        total, _ = WindowLoss(m, TrainConfig(feedback_grad=feedback_grad, w_vertex=0.0))(w)
        total.backward()
        return total.detach(), {n: p.grad.clone() for n, p in m.named_parameters()}

    # stop: the frames depend on the first one only through the residual, d(last)/d(first) = I
    first = w[:, 0].clone().requires_grad_(True)
    for feedback_grad, identity in ((False, True), (True, False)):
        frames = m.rollout(first, 4, m.initial_state(3), sample=False, feedback_grad=feedback_grad)[0]
        (g,) = torch.autograd.grad(frames[:, -1].sum(), first)
        assert torch.equal(g, torch.ones_like(g)) == identity

    full_loss, _ = run("full")
    stop_loss, stop = run("stop")
    assert abs(float(stop_loss) - float(full_loss)) <= 1e-6 * abs(float(full_loss))
    monkeypatch.setattr(m, "rollout", lambda first, steps, state, sample=False, n_forward=None, feedback_grad=True:
                        _reference_rollout_fed_back_as_constants(m, first, steps, state, n_forward))
    ref_loss, ref = run("stop")
    assert abs(float(stop_loss) - float(ref_loss)) <= 1e-5 * abs(float(ref_loss))
    for n in ref:
        err = (stop[n] - ref[n]).norm() / ref[n].norm()
        assert err <= 1e-5, f"{n}: relative error {float(err):.2e}"


@pytest.mark.parametrize("layers", [1, 3])
def test_lstm_step_is_one_step_of_the_stacked_module(layers):
    """``lstm_step`` (torch.lstm_cell layer by layer) computes what ``nn.LSTM`` computes for one time
    step, output, state and every gradient, to float32 rounding."""
    torch.manual_seed(layers)
    lstm = torch.nn.LSTM(12, 12, layers)
    z, h, c = torch.randn(5, 12, requires_grad=True), torch.randn(layers, 5, 12), torch.randn(layers, 5, 12)
    out, (h2, c2) = lstm_step(lstm, z, h, c)
    ref, (h_ref, c_ref) = lstm(z.unsqueeze(0), (h, c))
    for a, b in ((out, ref[0]), (h2, h_ref), (c2, c_ref)):
        torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-5)
    w = torch.randn(12)
    grads = torch.autograd.grad((out @ w).sum() + c2.sum(), [z, *lstm.parameters()])
    grads_ref = torch.autograd.grad((ref[0] @ w).sum() + c_ref.sum(), [z, *lstm.parameters()])
    for g, g_ref in zip(grads, grads_ref):
        torch.testing.assert_close(g, g_ref, atol=1e-6, rtol=1e-5)

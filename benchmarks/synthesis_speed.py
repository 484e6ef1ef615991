"""Benchmark: synthesis speed on CPU (diverse completion), against this machine's floors.

For models of the paper's size (latent 128, 3 LSTM layers, 3 conv layers; random weights: the
speed does not depend on the values) on twisting-limb meshes of about 3,000 and 10,000 vertices,
and for 1 and 8 samples, prints:

- the model step: ms per roll-out step of a completion (K forward + K backward chains, one batch)
  and per generated frame of one sample, beside its floor: the bytes of the weights one step reads
  (the big FC twice: encoder and tied decoder, plus the LSTM and head) over the machine's copy
  rate measured in the same run (a 256 MB numpy copy);
- reconstruction: ms per generated frame of ``assemble_vertices`` (features -> vertices through
  the keys) for all K samples, beside ``acap.Reconstructor.solve``'s time per frame on the same
  mesh measured in the same run (benchmarks/acap_speed.py's reconstruct figure);
- the whole completion of a 30-frame gap through the Python API (``Model.complete``), warm;
- for the numpy backend's one-sample step, where it goes: the two products with the big FC weight
  (their GB/s against the copy rate) and the rest (mesh convolutions, LSTM, head): the measured
  reason when the step misses its floor target.

Each figure for both inference backends: ``numpy`` (``meshseq.numpy_net``: what ``meshseq predict``
and ``complete`` run on CPU, and ``meshseq.load(run, backend="numpy")``) and ``torch`` (the
``BDLSTM`` module, ``meshseq.load(run)``'s default). Each target is judged on both backends: the
Python API runs torch unless asked (``meshseq.load``'s default), the commands run numpy.

Targets (2 cores): step within 2x its floor at 1 sample; at 8 samples within 1.5x of the 1-sample
time per step; 30-frame gap, 8 samples, 10k vertices: at most 2 s through the API.

``--command RUN DATA`` also times ``meshseq complete RUN DATA --keyframes 0,31 --samples 8`` as a
command (start-up and loading included; target 4 s on crane).

    python benchmarks/synthesis_speed.py [--repeat 5] [--backends numpy,torch] [--command RUN crane.npz]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy loads, as the commands run (device.inference_setup)
import numpy as np  # noqa: E402
import torch  # noqa: E402

from meshseq.acap import Scaling, extract
from meshseq.api import Model
from meshseq.data.synthetic import twisting_limb
from meshseq.mesh import Topology
from meshseq.model import BDLSTM, ModelConfig
from meshseq.model_config import tensor_shapes
from meshseq.numpy_net import NumpyNet, ring_matrix
from meshseq import synthesize

sys.path.insert(0, str(Path(__file__).resolve().parent))
from acap_speed import best_of  # noqa: E402  (a sibling script: the benchmarks share their timer)

MESHES = {"3k": (75, 40), "10k": (125, 80)}  # rings, segments: 3,002 and 10,002 vertices
GAP = 30


def machine_rates(repeat: int) -> tuple[float, float]:
    """(float32 matmul GFLOP/s on torch's threads, streaming copy GB/s counting read + write)."""
    n = 2048
    a, b = torch.rand(n, n), torch.rand(n, n)
    t, _ = best_of(repeat, lambda: a @ b)
    gflops = 2 * n**3 / t / 1e9
    x = np.random.rand(1 << 25)  # 256 MB
    y = np.empty_like(x)
    t, _ = best_of(repeat, lambda: np.copyto(y, x))
    return gflops, 2 * x.nbytes / t / 1e9


def random_model(rings: int, segments: int) -> tuple[dict[str, Model], np.ndarray]:
    """A paper-sized model with random weights on a twisting limb as ``{backend: Model}`` (the same
    weights), and the limb's vertices (T, V, 3)."""
    seq = twisting_limb(frames=40, rings=rings, segments=segments)
    topo = Topology.from_faces(seq.faces, seq.n_vertices)
    torch.manual_seed(0)
    config = ModelConfig(n_vertices=seq.n_vertices, latent=128, lstm_layers=3, conv_layers=3,
                         input_norm=True, logvar_max=0.0)
    net = BDLSTM(config, topo)
    feats = extract(seq.vertices, seq.faces)
    scaling = Scaling.fit(feats)
    net.set_input_norm(scaling.apply(feats))
    meta = {"scaling": scaling.to_dict()}
    weights, ring = {k: v.numpy() for k, v in net.state_dict().items()}, ring_matrix(topo)
    # numpy: with the compiled mesh convolution where it builds (meshseq.native); numpy-plain: numpy's layers
    return {"numpy": Model(NumpyNet(config, weights, ring), meta, seq.vertices[0], seq.faces, "cpu"),
            "numpy-plain": Model(NumpyNet(config, weights, ring, compiled=False), meta, seq.vertices[0], seq.faces,
                                 "cpu"),
            "torch": Model(net, meta, seq.vertices[0], seq.faces, "cpu")}, seq.vertices


def step_bytes(config: ModelConfig) -> int:
    """Bytes of the weights one step reads: the big FC twice (encoder, tied decoder), the rest once
    (the input normalisation and the unused log-variance head left out)."""
    shapes = tensor_shapes(config)
    skip = ("fc_logvar.weight", "fc_logvar.bias", "input_offset", "input_spread")
    return 4 * (sum(int(np.prod(s)) for n, s in shapes.items() if n not in skip) + int(np.prod(shapes["fc.weight"])))


def time_steps(model: Model, keys: np.ndarray, samples: int, repeat: int) -> float:
    """Seconds per roll-out step of a completion's chains (K forward + K backward rows), through
    ``model.engine`` (either backend)."""
    a, b = (np.asarray(k, dtype=np.float32) for k in keys)
    first = np.concatenate([np.repeat(a[None], samples, 0), np.repeat(b[None], samples, 0)])
    state = model.engine.initial_state(samples, samples)
    steps = GAP + 1
    t, _ = best_of(repeat, lambda: model.engine.rollout(first, steps, state, n_forward=samples))
    return t / steps


def time_reconstruction(model: Model, feats: np.ndarray, verts: np.ndarray, samples: int, repeat: int) -> float:
    """Seconds to turn ``samples`` completions (GAP + 2 frames each) into vertices through the keys."""
    n = GAP + 2
    f = np.stack([feats[:n]] * samples)  # (K, n, V, 9)
    anchors = {0: verts[0], n - 1: verts[n - 1]}
    t, _ = best_of(repeat, lambda: synthesize.assemble_vertices(model, f, anchors))  # one batched call
    return t


def time_command(run: str, data: str, repeat: int) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        times = []
        for i in range(repeat):
            out = Path(tmp) / f"out{i}"
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-m", "meshseq", "complete", run, data, "--keyframes", f"0,{GAP + 1}",
                            "--samples", "8", "-o", str(out)], check=True, capture_output=True)
            times.append(time.perf_counter() - t0)
    return min(times)


def time_fc_products(net: NumpyNet, rows: int, repeat: int) -> tuple[float, float]:
    """Seconds of one step's two products with the big FC weight on the numpy backend for ``rows``
    chains: the encoder's ``W x`` and the tied decoder's ``W^T h`` (as ``NumpyNet`` runs them below
    ``COMPILED_MIN_CHAINS``)."""
    rng = np.random.default_rng(0)
    L, N = net.fc_weight.shape
    xt = rng.standard_normal((rows, N)).astype(np.float32).T  # (N, rows), laid out as the step's frames
    h = rng.standard_normal((rows, L)).astype(np.float32)
    t_enc, _ = best_of(repeat, lambda: net._fc_encode(xt))
    t_dec, _ = best_of(repeat, lambda: net._fc(h, net.fc_weight, net.dec_bias))
    return t_enc, t_dec


def step_split(model: Model, step: float, gbs: float, repeat: int) -> None:
    """Print where the numpy backend's one-sample step goes: the FC products against the time their
    bytes take at the copy rate, and the rest (mesh convolutions, LSTM, head)."""
    t_enc, t_dec = time_fc_products(model.net, 2, repeat)
    fc_bytes = 2 * 4 * model.net.fc_weight.size
    print(f"        of the step: FC products {(t_enc + t_dec) * 1e3:5.2f} ms (encoder {t_enc * 1e3:.2f}, decoder "
          f"{t_dec * 1e3:.2f}; {fc_bytes / (t_enc + t_dec) / 1e9:.1f} GB/s, {fc_bytes / (gbs * 1e9) * 1e3:.2f} ms at the "
          f"copy rate), the rest (convolutions, LSTM, head) {(step - t_enc - t_dec) * 1e3:5.2f} ms")


def time_backend(name: str, backend: str, model: Model, verts: np.ndarray, feats: np.ndarray, keys: np.ndarray,
                 floor: float, solve_frame: float, repeat: int, gbs: float) -> list[tuple[str, float, float]]:
    """Print one backend's figures at 1 and 8 samples; return its targets ``(what, value, limit)``."""
    targets, one_step = [], None
    for samples in (1, 8):
        step = time_steps(model, keys, samples, repeat)
        one_step = one_step or step
        rec_frame = time_reconstruction(model, feats, verts, samples, repeat) / (samples * (GAP + 2))
        t_api, _ = best_of(max(2, repeat // 2), lambda: model.complete(verts[[0, GAP + 1]], GAP, samples=samples,
                                                                      seed=0))
        print(f"  {backend:5s} K={samples}: step {step * 1e3:6.2f} ms ({step / floor:4.2f}x floor, "
              f"{step / one_step:4.2f}x K=1), {step / samples * 1e3:5.2f} ms per generated frame | "
              f"reconstruction {rec_frame * 1e3:5.2f} ms per generated frame ({rec_frame / solve_frame:4.2f}x solve) | "
              f"API complete {GAP}-frame gap {t_api:5.2f} s")
        print(f"        of the API completion: roll-out {step * (GAP + 1):4.2f} s, reconstruction "
              f"{rec_frame * samples * (GAP + 2):4.2f} s, other "
              f"{t_api - step * (GAP + 1) - rec_frame * samples * (GAP + 2):4.2f} s")
        if samples == 1 and isinstance(model.net, NumpyNet):
            step_split(model, step, gbs, repeat)
        if samples == 1:
            targets.append((f"{name} {backend}: step at K=1 within 2x its floor", step / floor, 2.0))
        else:
            targets.append((f"{name} {backend}: step at K=8 within 1.5x of K=1", step / one_step, 1.5))
            if name == "10k":
                targets.append((f"{name} {backend}: API completion of a {GAP}-frame gap, 8 samples, s", t_api, 2.0))
    return targets


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--meshes", default=",".join(MESHES), help="which of 3k,10k")
    ap.add_argument("--backends", default="numpy,torch", help="which of numpy,numpy-plain,torch (numpy: with the "
                    "compiled mesh convolution where it builds; numpy-plain: numpy's layers)")
    ap.add_argument("--command", nargs=2, metavar=("RUN", "DATA"), default=None,
                    help="also time `meshseq complete RUN DATA --samples 8` of a 30-frame gap")
    ap.add_argument("--threads", type=int, default=None,
                    help="torch threads (default: torch's choice, one per core); 1 gives steadier figures on a "
                         "machine shared with other work (the kernels' OpenMP threads wait for each other)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    gflops, gbs = machine_rates(args.repeat)
    from meshseq import native

    print(f"machine: float32 matmul {gflops:.1f} GFLOP/s, copy {gbs:.1f} GB/s (read + write); "
          f"torch threads {torch.get_num_threads()}; compiled mesh convolution "
          f"{'built' if native.conv_library() else 'NOT available (numpy = numpy-plain)'}")
    targets = []
    backends = args.backends.split(",")
    for name in args.meshes.split(","):
        models, verts = random_model(*MESHES[name])
        first = models[backends[0]]
        V = first.config.n_vertices
        feats = first.features(verts)
        keys = feats[[0, GAP + 1]]
        floor = step_bytes(first.config) / (gbs * 1e9)
        t_solve, _ = best_of(args.repeat, lambda: first.vertices(feats))
        solve_frame = t_solve / len(feats)
        print(f"{name} ({V} vertices): step weights {step_bytes(first.config) / 1e6:.1f} MB -> floor "
              f"{floor * 1e3:.2f} ms; Reconstructor.solve {solve_frame * 1e3:.2f} ms/frame ({len(feats)} frames, "
              f"acap_speed's figure)")
        for backend in backends:
            targets += time_backend(name, backend, models[backend], verts, feats, keys, floor, solve_frame, args.repeat,
                                    gbs)
    if args.command:
        t = time_command(*args.command, max(1, args.repeat // 2))
        print(f"command: meshseq complete {args.command[0]} {args.command[1]} --samples 8, {GAP}-frame gap: {t:.2f} s")
        targets.append(("command, s", t, 4.0))
    for what, value, limit in targets:
        print(f"target {what}: {value:.2f} (<= {limit}) {'met' if value <= limit else 'NOT met'}")


if __name__ == "__main__":
    main()

"""DistributedDataParallel training: two CPU processes (Gloo) on loopback, started by torchrun."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import torch
from safetensors.torch import load_file

from meshseq.data.synthetic import twisting_limb
from meshseq.io import save_sequence

RANK_SCRIPT = r"""
import json, os, sys
import torch
torch.set_num_threads(1)
from safetensors.torch import save_file
from meshseq.train import TrainConfig, load_training_data, train

data_path, run, out = sys.argv[1:4]
rank = int(os.environ["RANK"])
torch.manual_seed(0)
data = load_training_data([data_path])
cfg = TrainConfig(iterations=4, window=6, batch=4, eval_every=2, checkpoint_every=2, log_every=1)
result = train(data, run, cfg, {"latent": 16, "lstm_layers": 2}, device="cpu", progress=False, log=None)
model = result["model"]
save_file({k: v.contiguous() for k, v in model.state_dict().items()}, os.path.join(out, f"rank{rank}.safetensors"))
with open(os.path.join(out, f"rank{rank}.json"), "w") as fh:
    json.dump({"world": int(os.environ["WORLD_SIZE"]), "iteration": result["iteration"],
               "loss": result["loss"]}, fh)
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_two_ranks(tmp_path, script_text: str, run) -> Path:
    """Run ``script_text`` as ``SCRIPT LIMB.npz RUN OUT`` on two Gloo CPU ranks on loopback (a
    small limb sequence as the data); returns OUT, where the ranks leave their results."""
    save_sequence(twisting_limb(frames=24, rings=8, segments=6), tmp_path / "limb.npz")
    script = tmp_path / "ranks.py"
    script.write_text(script_text)
    out = tmp_path / "out"
    out.mkdir()
    env = dict(os.environ, OMP_NUM_THREADS="1", GLOO_SOCKET_IFNAME="lo", MASTER_ADDR="127.0.0.1")
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nnodes", "1", "--nproc_per_node", "2",
           "--master_addr", "127.0.0.1", "--master_port", str(free_port()),
           str(script), str(tmp_path / "limb.npz"), str(run), str(out)]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out


def test_two_cpu_ranks_hold_identical_weights(tmp_path):
    run = tmp_path / "run"
    out = run_two_ranks(tmp_path, RANK_SCRIPT, run)
    w0, w1 = load_file(str(out / "rank0.safetensors")), load_file(str(out / "rank1.safetensors"))
    assert w0.keys() == w1.keys()
    for k in w0:
        assert torch.equal(w0[k], w1[k]), k
    info = [json.loads((out / f"rank{r}.json").read_text()) for r in (0, 1)]
    assert [(i["world"], i["iteration"]) for i in info] == [(2, 4), (2, 4)]
    # each rank trained on its own half of the batch (different windows and noise), so the equal
    # weights come from the gradient all-reduce, not from identical work
    assert info[0]["loss"] != info[1]["loss"]
    # rank 0 wrote the checkpoints, which hold the same weights; training changed them
    ck = load_file(str(run / "checkpoints" / "00000004" / "model.safetensors"))
    first = load_file(str(run / "checkpoints" / "00000002" / "model.safetensors"))
    for k in w0:
        assert torch.equal(ck[f"model.{k}"], w0[k]), k
    assert not torch.equal(ck["model.fc.weight"], first["model.fc.weight"])
    meta = json.loads((run / "checkpoints" / "00000004" / "model.json").read_text())
    assert meta["world_size"] == 2
    assert 0.0 <= meta["completion"]["vertex_share"] <= 1.0  # fitted once, by rank 0, which writes model.json


RESUME_SCRIPT = r"""
import json, os, sys
import numpy as np
import torch
torch.set_num_threads(1)
import torch.distributed as dist
from safetensors.torch import save_file
from meshseq.train import TrainConfig, load_training_data, train

data_path, root, out = sys.argv[1:4]
rank = int(os.environ["RANK"])
dist.init_process_group("gloo")  # kept open over the three runs (train() leaves it to us)
data = load_training_data([data_path])
cfg = dict(window=6, batch=4, eval_every=0, checkpoint_every=2, log_every=1, w_kl=0.1)
opts = {"latent": 16, "lstm_layers": 1}
one = train(data, os.path.join(root, "a"), TrainConfig(iterations=4, **cfg), opts, device="cpu", progress=False,
            log=None)
train(data, os.path.join(root, "b"), TrainConfig(iterations=2, **cfg), opts, device="cpu", progress=False, log=None)
torch.randn(100 * (rank + 1))  # the global generators move on differently per rank in between
np.random.default_rng().random()
two = train(data, os.path.join(root, "b"), TrainConfig(iterations=4, **cfg), opts, device="cpu", resume=True,
            progress=False, log=None)
for name, res in (("one", one), ("two", two)):
    state = {k: v.contiguous() for k, v in res["model"].state_dict().items()}
    state["rng"] = torch.get_rng_state()
    save_file(state, os.path.join(out, f"{name}{rank}.safetensors"))
dist.destroy_process_group()
"""


def test_two_cpu_ranks_resume_bit_for_bit(tmp_path):
    """4 iterations on two ranks = 2 iterations + resume + 2 more: weights, every rank's
    generator and the checkpoints' tensors agree exactly."""
    out = run_two_ranks(tmp_path, RESUME_SCRIPT, tmp_path)
    for rank in (0, 1):
        one, two = load_file(str(out / f"one{rank}.safetensors")), load_file(str(out / f"two{rank}.safetensors"))
        assert one.keys() == two.keys()
        for k in one:
            assert torch.equal(one[k], two[k]), (rank, k)
    a = {**load_file(str(tmp_path / "a/checkpoints/00000004/model.safetensors")),
         **load_file(str(tmp_path / "a/checkpoints/00000004/state.safetensors"))}
    b = {**load_file(str(tmp_path / "b/checkpoints/00000004/model.safetensors")),
         **load_file(str(tmp_path / "b/checkpoints/00000004/state.safetensors"))}
    assert a.keys() == b.keys() and {"rng.torch", "rng.torch.rank1"} <= a.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    assert not torch.equal(a["rng.torch"], a["rng.torch.rank1"])  # each rank's own noise

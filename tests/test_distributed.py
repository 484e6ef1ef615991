"""DistributedDataParallel training: two CPU processes (Gloo) on loopback, started by torchrun."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys

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


def test_two_cpu_ranks_hold_identical_weights(tmp_path):
    seq = twisting_limb(frames=24, rings=8, segments=6)
    save_sequence(seq, tmp_path / "limb.npz")
    script = tmp_path / "rank.py"
    script.write_text(RANK_SCRIPT)
    run, out = tmp_path / "run", tmp_path / "out"
    out.mkdir()
    env = dict(os.environ, OMP_NUM_THREADS="1", GLOO_SOCKET_IFNAME="lo", MASTER_ADDR="127.0.0.1")
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nnodes", "1", "--nproc_per_node", "2",
           "--master_addr", "127.0.0.1", "--master_port", str(free_port()),
           str(script), str(tmp_path / "limb.npz"), str(run), str(out)]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-3000:]
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

"""``meshseq train``: train a BD-LSTM on one or more mesh sequences."""

from __future__ import annotations

import argparse
from pathlib import Path

#: the names of meshseq.train.RECIPES (kept here so that --help does not import torch)
RECIPE_NAMES = ("default", "paper")


def register(sub) -> None:
    """Add this module's sub-commands to the ``meshseq`` parser's ``sub`` (argparse subparsers)."""
    p = sub.add_parser(
        "train",
        help="train a BD-LSTM on mesh sequences",
        description="Train the bidirectional LSTM generator (shared-weight chains, tied mesh-convolutional "
        "VAE) on ACAP features of one or more mesh sequences with one connectivity. Writes checkpoints "
        "(safetensors + JSON), metrics.csv and, if tensorboard is installed, TensorBoard events to RUN. "
        "Under torchrun it trains with DistributedDataParallel "
        "(e.g. torchrun --nproc_per_node 4 $(which meshseq) train DATA --out RUN).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("data", nargs="+", metavar="DATA", help="mesh sequences (folder, .npz, FILE.h5:SEQ); "
                   "several must share one connectivity; the first frame of the first is the reference mesh")
    p.add_argument("--out", required=True, metavar="RUN", help="run folder for checkpoints and metrics")
    p.add_argument("--iterations", type=int, default=7000, help="training iterations (the paper: 7000)")
    p.add_argument("--variant", choices=("bd", "std-bd", "uni"), default="bd",
                   help="bd: shared-weight bidirectional chains; std-bd: two untied LSTMs; uni: forward only")
    p.add_argument("--window", type=int, default=32, help="frames per training window")
    p.add_argument("--batch", type=int, default=8, help="windows per iteration (over all processes)")
    p.add_argument("--stride", type=int, default=1, help="take every STRIDE-th frame (2: every other frame)")
    p.add_argument("--seed", type=int, default=0, help="random seed (weights, windows, sampling noise)")
    p.add_argument("--device", default="auto", help="auto (cuda if available), cpu, cuda or cuda:N")
    p.add_argument("--threads", type=int, default=None,
                   help="CPU threads for torch (default: torch's choice; 1 is best for tiny models)")
    p.add_argument("--precision", choices=("float32", "bf16"), default="float32",
                   help="bf16: autocast the training step to bfloat16 (float32 master weights; faster "
                        "on CPUs with AVX-512 BF16 and on GPUs; off by default)")
    p.add_argument("--resume", action="store_true", help="continue RUN from its newest undamaged checkpoint "
                   "(its stored options are used; --iterations may extend the run); an error if RUN has none")
    p.add_argument("--force", action="store_true", help="start over in a non-empty RUN (deletes the checkpoints, "
                   "metrics and TensorBoard events training wrote there, nothing else)")
    m = p.add_argument_group("model")
    m.add_argument("--latent", type=int, default=128, help="latent width = LSTM width")
    m.add_argument("--lstm-layers", type=int, default=3, help="LSTM layers")
    m.add_argument("--conv-layers", type=int, default=3, help="mesh convolution layers (9 -> 9, tanh)")
    m.add_argument("--conv", choices=("sparse", "gather"), default="sparse",
                   help="1-ring mean of the reference conv layer (MeshConv.forward, used by single "
                        "encode/decode/step calls): sparse matrix or padded gather; roll-outs (training, "
                        "prediction) always use the fused kernel (meshseq.kernels)")
    l = p.add_argument_group("recipe, loss and optimiser (unset options come from --recipe)")
    l.add_argument("--recipe", choices=sorted(RECIPE_NAMES), default="default",
                   help="default: meshseq's measured recipe (see docs/results.md); paper: the paper's "
                   "literal recipe (its L_2 collapses the latent and roll-outs freeze)")
    l.add_argument("--lr", type=float, default=1e-3, help="Adam learning rate")
    l.add_argument("--adam-beta2", type=float, default=0.999,
                   help="Adam's second-moment decay (0.999: TensorFlow's and torch's default)")
    l.add_argument("--w-rec", type=float, default=None, help="weight of L_rec")
    l.add_argument("--w-bd", type=float, default=None, help="weight of L_bd (ignored by --variant uni)")
    l.add_argument("--w-kl", type=float, default=None, help="weight of L_KL")
    l.add_argument("--w-l2", type=float, default=None, help="weight of L_2 (sum of squared weights)")
    l.add_argument("--w-motion", type=float, default=None,
                   help="weight of L_motion (generated frame-to-frame change vs the truth's, in size; "
                   "not in the paper: 0 in its recipe, 20 in the default one)")
    l.add_argument("--w-vertex", type=float, default=None,
                   help="weight of L_vertex (generated frames reconstructed to vertices against the truth's, "
                   "in the feature loss's units; not in the paper: 0 in its recipe, 1 in the default one)")
    l.add_argument("--vertex-frames", type=int, default=4, metavar="N",
                   help="with --w-vertex: frames of each chain that L_vertex reconstructs, evenly spaced, "
                   "the last always (each costs a sparse solve per iteration)")
    l.add_argument("--given", type=int, default=None, help="teacher-forced first frames per chain: "
                   "each iteration draws 1..GIVEN (1 = the paper's free-running chains)")
    l.add_argument("--input-norm", action=argparse.BooleanOptionalAction, default=None,
                   help="normalise the encoder's input (frames centred on the mean training frame, unit "
                   "spread per channel); the default recipe does, the paper's does not")
    l.add_argument("--step-scale", choices=("none", "data"), default=None,
                   help="none: X' = X + dX (the paper); data: X' = X + s dX with s the RMS frame-to-frame "
                   "change of each channel in the training data")
    l.add_argument("--fc-lr", choices=("fan-in", "encoder", "none"), default=None,
                   help="how the big FC weight learns on large meshes, with f = min(1, N / (vertices x 9)) "
                   "and N from --fc-lr-fan-in: fan-in: its learning rate times f; encoder: one rate, the "
                   "encoder's share of its gradient times f (the decoder's untouched); none: one rate for "
                   "all (the paper)")
    l.add_argument("--fc-lr-fan-in", type=int, default=None, metavar="N",
                   help="with --fc-lr fan-in or encoder: the FC fan-in (vertices x 9) from which the rule acts "
                   "(9000)")
    l.add_argument("--kl-scale", choices=("vertices", "none"), default=None,
                   help="vertices: the weight of L_KL times vertices / 1000, so its balance with the "
                   "per-vertex sums of L_rec does not depend on the mesh size (the default recipe); "
                   "none: --w-kl as given (the paper)")
    l.add_argument("--logvar-max", type=_number_or_none, default=None, metavar="X|none",
                   help="clamp the encoder's log-variance to at most X, so the sampling noise never "
                   "exceeds exp(X / 2) (the default recipe: 0, the prior's spread); none: unbounded "
                   "(the paper)")
    l.add_argument("--mu-max", type=_number_or_none, default=None, metavar="X|none",
                   help="squash the latent mean softly into (-X, X) (X tanh(mu / X)), so a large step on "
                   "the encoder cannot throw the latent far outside the prior; none: unbounded (both recipes)")
    l.add_argument("--grad-clip", type=_number_or_none, default=None, metavar="X|none",
                   help="clip the gradient's norm at X times the median norm of the last 100 iterations, "
                   "so one exploding roll-out cannot throw the weights far; none: no clipping (both recipes)")
    l.add_argument("--ema-decay", type=_number_or_none, default=None, metavar="X|none",
                   help="checkpoints deliver an exponential moving average of the weights with decay X "
                   "(about the last 1 / (1 - X) iterations), so a loss spike near the end does not reach "
                   "the delivered model; none: the last weights (the paper)")
    l.add_argument("--window-fit", choices=("batch", "none"), default=None,
                   help="batch (default recipe): shorten --window until the training frames hold at least "
                   "--batch different windows (short sequences; never below 16 frames while that fits); "
                   "none (--recipe paper): the window as given")
    l.add_argument("--feedback-grad", choices=("full", "stop"), default=None,
                   help="full: backpropagate through the generated frames fed back into the encoder (both "
                   "recipes, the paper); stop: each fed-back frame is a constant input, so the gradient "
                   "does not loop through the mesh features (it still flows through the LSTM state)")
    l.add_argument("--no-kl", action="store_true", help="drop L_KL (paper Table 1 ablation)")
    l.add_argument("--no-l2", action="store_true", help="drop L_2 (paper Fig. 3 ablation)")
    d = p.add_argument_group("data")
    d.add_argument("--holdout", type=float, default=0.2, help="fraction of every data set held out (one block)")
    d.add_argument("--holdout-at", default="end", help="where the held-out block starts: start, end or a fraction")
    d.add_argument("--validation", type=float, default=0.0, metavar="F",
                   help="keep the last F of every data set's training frames out of training as a validation "
                   "block; every --eval-every iterations ours' prediction error there (1 and 3 given frames, "
                   "horizons up to 15) is measured and the best checkpoint kept as RUN/checkpoints/best "
                   "(default 0: none)")
    d.add_argument("--speed-augment", type=float, default=1.0, metavar="R",
                   help="play every training window at a random speed in [1/R, R] (log-uniform; each frame "
                   "the linear interpolation of the two around it), a temporal-resampling augmentation for "
                   "few sequences (default 1: off, as the paper)")
    d.add_argument("--scaling", choices=("two-group", "per-channel", "robust"), default="two-group",
                   help="feature scaling to [-0.95, 0.95], fitted on the training frames")
    d.add_argument("--consistency", choices=("temporal", "spatial"), default="temporal",
                   help="rotation consistency of the ACAP features")
    o = p.add_argument_group("logging")
    o.add_argument("--eval-every", type=int, default=100, help="held-out loss every K iterations (0: at the end)")
    o.add_argument("--checkpoint-every", type=int, default=500, help="checkpoint every K iterations (and at the end)")
    o.add_argument("--log-every", type=int, default=10, help="write metrics every K iterations")
    o.add_argument("--keep", type=int, default=2, help="checkpoints kept (newest)")
    o.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_train)


def _number_or_none(text: str):
    """``--logvar-max`` / ``--mu-max`` / ``--grad-clip`` / ``--ema-decay`` values: a number, or ``none`` (off; kept apart from "not given")."""
    if text.lower() == "none":
        return _UNBOUNDED
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number or none, got {text!r}") from None


#: ``--logvar-max none``, ``--grad-clip none``: distinct from the option's default (None = take it from --recipe) and
#: from every other option's "none" string (an object of its own, so no interned "none" is it)
_UNBOUNDED = object()


def _train(args) -> int:
    from meshseq.errors import MeshseqError
    from meshseq.io import check_writable
    from meshseq.model import ModelConfig
    from meshseq.train import TrainConfig, load_training_data, train

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise MeshseqError(f"--out {out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not (args.resume or args.force):
        raise MeshseqError(f"--out {out}: already exists and is not empty (use --resume to continue it "
                           "or --force to start over)")
    check_writable(f"--out {out}", out)
    from meshseq.train import RECIPE_OPTIONS, RECIPES

    recipe = dict(RECIPES[args.recipe])
    for name in RECIPE_OPTIONS:
        if getattr(args, name) is not None:
            recipe[name] = None if getattr(args, name) is _UNBOUNDED else getattr(args, name)
    if args.no_kl:
        recipe["w_kl"] = 0.0
    if args.no_l2:
        recipe["w_l2"] = 0.0
    config = TrainConfig(
        iterations=args.iterations, window=args.window, batch=args.batch, stride=args.stride, seed=args.seed,
        lr=args.lr, adam_beta2=args.adam_beta2, holdout=args.holdout, holdout_at=args.holdout_at,
        validation=args.validation, speed_augment=args.speed_augment, scaling=args.scaling,
        consistency=args.consistency, eval_every=args.eval_every,
        checkpoint_every=args.checkpoint_every, log_every=args.log_every, keep=args.keep,
        precision=args.precision, vertex_frames=args.vertex_frames, **recipe,
    )
    if args.threads is not None:
        if args.threads < 1:
            raise MeshseqError(f"--threads {args.threads}: expected a positive integer")
        import torch

        torch.set_num_threads(args.threads)
    model_options = {"variant": args.variant, "latent": args.latent, "lstm_layers": args.lstm_layers,
                     "conv_layers": args.conv_layers, "conv_impl": args.conv}
    ModelConfig.check_options(model_options)  # every option is checked before the data is loaded
    consistency = args.consistency
    if args.resume and not args.force:  # features as the run was trained on (its stored options)
        from meshseq.train import resume_point

        consistency = resume_point(out).meta["train"]["consistency"]
    data = load_training_data(args.data, consistency=consistency)
    created = not out.exists()
    try:
        result = train(data, out, config, model_options, device=args.device, resume=args.resume,
                       force=args.force, progress=not args.no_progress)
    except MeshseqError:
        # an error that needs the data (e.g. --window longer than it) is found after train()
        # created RUN: leave no empty folder behind
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()
        raise
    if result.get("checkpoint") and (not _dist_rank()):
        held = result.get("heldout_rec")
        print(f"trained to iteration {result['iteration']}: loss {result['loss']}"
              + (f", held-out L_rec {held:.4g}" if held is not None else "")
              + f"; checkpoint {result['checkpoint']}")
        if "best" in result:
            best = result["best"]
            print(f"best on the validation block: iteration {best['iteration']} (error {best['error']:.1f} x 1e-4); "
                  f"checkpoint {best['checkpoint']}")
    return 0


def _dist_rank() -> int:
    import os

    return int(os.environ.get("RANK", "0"))

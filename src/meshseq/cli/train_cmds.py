"""``meshseq train``: train a BD-LSTM on one or more mesh sequences."""

from __future__ import annotations

from pathlib import Path

#: the names of meshseq.train.RECIPES (kept here so that --help does not import torch)
RECIPE_NAMES = ("default", "paper")


def register(sub) -> None:
    """Add this module's sub-commands to the ``meshseq`` parser's ``sub`` (argparse subparsers)."""
    p = sub.add_parser(
        "train",
        help="train a BD-LSTM on mesh sequences",
        description="Train the bidirectional LSTM generator on the ACAP features of one or more mesh sequences "
        "with one connectivity. Writes checkpoints, metrics.csv and (with tensorboard installed) TensorBoard "
        "events to RUN. Under torchrun it trains with DistributedDataParallel "
        "(torchrun --nproc_per_node 4 $(which meshseq) train DATA --out RUN).",
        epilog="Every other option (loss weights, optimiser, data split, augmentation, logging) is set in "
        "--config FILE.toml as 'name = value' lines (e.g. w_motion = 10.0, eval_every = 50, ema_decay = \"none\"), "
        "with a [model] table for lstm_layers, conv_layers, conv_impl; the fields are documented in "
        "'python -m pydoc meshseq.training.config.TrainConfig'. Precedence: recipe < file < command line.",
    )
    p.add_argument("data", nargs="+", metavar="DATA", help="mesh sequences (folder, .npz, FILE.h5:SEQ, .glb, "
                   ".usd, .pc2/.mdd); several must share one connectivity")
    p.add_argument("--out", required=True, metavar="RUN", help="run folder for checkpoints and metrics")
    p.add_argument("--iterations", type=int, default=None, help="training iterations (default 7000, the paper's)")
    p.add_argument("--variant", choices=("bd", "std-bd", "uni"), default=None,
                   help="bd (default): shared-weight bidirectional chains; std-bd: two LSTMs; uni: forward only")
    p.add_argument("--window", type=int, default=None, help="frames per training window (default 32)")
    p.add_argument("--batch", type=int, default=None, help="windows per iteration, over all processes (default 8)")
    p.add_argument("--latent", type=int, default=None, help="latent width = LSTM width (default 128)")
    p.add_argument("--seed", type=int, default=None, help="random seed (default 0)")
    p.add_argument("--device", default="auto", help="auto (default: cuda if available), cpu, cuda or cuda:N")
    p.add_argument("--threads", type=int, default=None, help="CPU threads for torch (default: torch's choice)")
    p.add_argument("--precision", choices=("float32", "bf16"), default=None,
                   help="bf16: autocast the training step to bfloat16 (default float32)")
    p.add_argument("--validation", type=float, default=None, metavar="F",
                   help="keep the last F of the training frames out to pick the best checkpoint on "
                   "(RUN/checkpoints/best; default 0: none)")
    p.add_argument("--recipe", choices=RECIPE_NAMES, default="default",
                   help="default: meshseq's measured recipe; paper: the paper's literal one")
    p.add_argument("--config", metavar="FILE.toml", help="any other training option (see below)")
    p.add_argument("--resume", action="store_true", help="continue RUN from its newest checkpoint, with its "
                   "stored options (--iterations may extend it)")
    p.add_argument("--force", action="store_true", help="start over in a non-empty RUN (deletes only what "
                   "training wrote there)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_train)


#: the command line's TrainConfig fields (None: not given, the recipe's or the file's value)
_TRAIN_FLAGS = ("iterations", "window", "batch", "seed", "precision", "validation")


def train_options(args) -> tuple[object, dict]:
    """``(TrainConfig, model options)`` of ``meshseq train``'s arguments: the recipe, then the
    ``--config`` file, then the flags given."""
    from meshseq.training.config import RECIPES, TrainConfig, config_from_toml

    options = dict(RECIPES[args.recipe])
    model_options = {}
    if args.config is not None:
        from_file, model_options = config_from_toml(args.config, base=options)
        options.update(from_file)
    options.update({k: getattr(args, k) for k in _TRAIN_FLAGS if getattr(args, k) is not None})
    model_options.update({k: getattr(args, k) for k in ("variant", "latent") if getattr(args, k) is not None})
    return TrainConfig(**options), model_options


def _train(args) -> int:
    from meshseq.checkpoint_schema import feature_options
    from meshseq.errors import MeshseqError
    from meshseq.io import check_writable
    from meshseq.model import ModelConfig
    from meshseq.train import load_training_data, resume_meta, train

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise MeshseqError(f"--out {out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not (args.resume or args.force):
        raise MeshseqError(f"--out {out}: already exists and is not empty (use --resume to continue it "
                           "or --force to start over)")
    check_writable(f"--out {out}", out)
    config, model_options = train_options(args)
    if args.threads is not None:
        if args.threads < 1:
            raise MeshseqError(f"--threads {args.threads}: expected a positive integer")
        import torch

        torch.set_num_threads(args.threads)
    ModelConfig.check_options(model_options)  # every option is checked before the data is loaded
    consistency, placement = config.consistency, config.placement
    if args.resume and not args.force:  # features as the run was trained on (its stored options)
        consistency, placement = feature_options(resume_meta(out))
    data = load_training_data(args.data, consistency=consistency, placement=placement)
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

"""``meshseq demo``: the README's main job (see meshseq.demo), and a quick ACAP round-trip table."""

from __future__ import annotations

from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("demo", help="run the built-in demonstration (no data needed)",
                       description="Prepare the built-in data (human bodies from the Anny model when "
                       "available, else a generated limb), train a small model for a few minutes, predict "
                       "and complete held-out motion, compare with baselines, and write film strips, a GIF, "
                       "a .glb and the error table into one folder. --quick instead prints the ACAP "
                       "feature round trip on a generated limb (seconds).")
    p.add_argument("-o", "--output", default="meshseq-demo", metavar="DIR",
                   help="folder for the results (default ./meshseq-demo)")
    p.add_argument("--iterations", type=int, default=300, help="training iterations (default 300)")
    p.add_argument("--data", choices=("auto", "bodies", "limb"), default="auto",
                   help="auto (bodies if the Anny model works here, else limb), bodies, or limb")
    p.add_argument("--device", default="auto", help="auto (CUDA if available), cpu or cuda")
    p.add_argument("--cache", default=None, metavar="DIR",
                   help="where built data is cached (default $MESHSEQ_CACHE or ~/.cache/meshseq)")
    p.add_argument("--force", action="store_true", help="replace DIR if it exists")
    p.add_argument("--quick", action="store_true", help="only the ACAP round-trip table (no training)")
    p.add_argument("--frames", type=int, default=48, help="--quick: frames of the generated limb (default 48)")
    p.set_defaults(func=cmd_demo)


def cmd_demo(args) -> int:
    from meshseq.errors import MeshseqError

    if args.quick:
        return quick_roundtrip(args.frames)
    if args.iterations < 1:
        raise MeshseqError(f"--iterations {args.iterations}: expected at least 1")
    from rich.console import Console

    from meshseq.demo import errors_markdown, run_demo

    console = Console()
    out = Path(args.output)
    result = run_demo(out, iterations=args.iterations, data=args.data, force=args.force, device=args.device,
                      cache=Path(args.cache) if args.cache else None,
                      log=lambda m: console.print(m, highlight=False))
    console.print(errors_markdown(result), highlight=False)
    console.print(f"[bold]done[/bold] in {result['total_seconds']:.0f} s (training {result['train_seconds']:.0f} s). "
                  f"Open {out}/prediction.gif, {out}/prediction.png, {out}/completion.png; "
                  f"{out}/prediction.glb in Blender or a browser; the table is {out}/errors.md.")
    console.print(f"Continue: [bold]meshseq predict {out}/run DATA --given 2 --frames 60 -o pred.npz[/bold]")
    return 0


def quick_roundtrip(frames: int) -> int:
    from rich.console import Console
    from rich.table import Table

    from meshseq.cli.acap_cmds import roundtrip_report
    from meshseq.data.synthetic import twisting_limb
    from meshseq.errors import MeshseqError

    if frames < 24:
        raise MeshseqError(f"--frames {frames}: the demo needs at least 24 frames")
    seq = twisting_limb(frames=frames)
    console = Console()
    console.print(f"[bold]meshseq demo --quick[/bold]: ACAP round trip on a generated limb "
                  f"({seq.n_frames} frames, {seq.n_vertices} vertices; twists 1.5 turns, bends past 90 degrees)")
    table = Table(title="extract -> reconstruct -> compare (error per vertex / bounding-box diagonal)")
    for col in ("encoding", "consistency", "mean error", "max error", "extract fps", "reconstruct fps"):
        table.add_column(col, justify="right" if "error" in col or "fps" in col else "left")
    for exact in (False, True):
        for consistency in ("temporal", "spatial"):
            r = roundtrip_report(seq, consistency=consistency, exact=exact)
            table.add_row("exact" if exact else "least squares", consistency, f"{r['mean_error_rel']:.2e}",
                          f"{r['max_error_rel']:.2e}", f"{r['extract_fps']:.0f}", f"{r['reconstruct_fps']:.0f}")
    console.print(table)
    return 0

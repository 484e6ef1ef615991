"""``meshseq make-bodies``: built-in human motion data from the Anny body model."""

from __future__ import annotations

import time

#: meshseq.data.motions.MOTIONS, kept here so that --help does not import numpy (a test checks they agree)
MOTIONS = ("walk", "jumping_jacks", "punch", "shake_arms", "squat", "wave", "bend")


def register(sub) -> None:
    """Add ``make-bodies`` to the ``meshseq`` parser's subparsers."""
    p = sub.add_parser(
        "make-bodies", help="generate human motion data (Anny bodies x motions) into a Dyna-style .h5",
        description="Pose Anny bodies (subjects of different build, sex and age) through built-in "
        f"motions ({', '.join(MOTIONS)}) and write every SUBJECT_MOTION sequence, with shared faces, "
        "to a Dyna-style HDF5 file readable as OUT.h5:SUBJECT_MOTION. Needs the bodies extra "
        "(pip install 'meshseq[bodies]'); Anny's first use on a machine builds its cache "
        "(a few minutes, ~790 MB in ~/.cache/anny or $ANNY_CACHE_DIR).")
    p.add_argument("--subjects", default="3", metavar="N|NAMES",
                   help="a count of sampled subjects (s00, s01, ...) or comma-separated names: "
                   "female_fit, male_heavy, female_old, male_fit, female_heavy, male_slim, "
                   "female_slim, male_old (default 3)")
    p.add_argument("--motions", default="all", metavar="LIST",
                   help=f"comma-separated motions or 'all' (default): {','.join(MOTIONS)}")
    p.add_argument("--frames", type=int, default=120, metavar="T", help="frames per sequence (default 120)")
    p.add_argument("--fps", type=float, default=30.0, help="frames per second of the motion (default 30)")
    p.add_argument("--vertices", type=int, default=3000, metavar="V",
                   help="vertices of the decimated template (default 3000); 0 for the full 13,348-vertex skin")
    p.add_argument("--seed", type=int, default=0, help="seed of the subjects and performances (default 0)")
    p.add_argument("--tempo", choices=("steady", "varied"), default="steady",
                   help="steady (default), or varied: holds, slow-downs to a stop and speed-ups in every sequence")
    p.add_argument("--parts", default="", metavar="LIST",
                   help="comma-separated separate parts carried by every body: eyes, strap (default none)")
    p.add_argument("-o", "--output", required=True, metavar="OUT.h5", help="output file (.h5)")
    p.add_argument("--force", action="store_true", help="overwrite OUT.h5 if it exists")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_make_bodies)


def cmd_make_bodies(args) -> int:
    from meshseq.data.accessories import resolve_parts
    from meshseq.data.bodies import body_model, make_body_set, resolve_motions, resolve_subjects
    from meshseq.errors import MeshseqError
    from meshseq.io import check_output

    if not str(args.output).lower().endswith((".h5", ".hdf5")):
        raise MeshseqError(f"-o {args.output}: the output must be a .h5 file")
    if args.frames < 2:
        raise MeshseqError(f"--frames {args.frames}: need at least 2 frames")
    if args.fps <= 0:
        raise MeshseqError(f"--fps {args.fps}: must be positive")
    if args.vertices < 0:
        raise MeshseqError(f"--vertices {args.vertices}: must be 0 (full resolution) or a vertex count")
    parts = resolve_parts(args.parts)
    check_output(args.output, force=args.force)
    subjects = resolve_subjects(args.subjects, seed=args.seed)
    motions = resolve_motions(args.motions)
    vertices = None if args.vertices == 0 else args.vertices
    total = len(subjects) * len(motions)
    start = time.perf_counter()
    if args.quiet:
        body_model()
        path = make_body_set(args.output, [s.name for s in subjects] if not args.subjects.strip().isdigit()
                             else len(subjects), motions, args.frames, vertices, seed=args.seed, fps=args.fps,
                             force=args.force, tempo=args.tempo, parts=parts)
    else:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                      TimeElapsedColumn(), transient=False) as progress:
            task = progress.add_task("loading Anny (first use builds its cache: minutes)", total=total)
            body_model()
            progress.update(task, description="posing bodies")

            def done(name: str) -> None:
                progress.update(task, advance=1, description=f"posing bodies ({name})")

            path = make_body_set(args.output, [s.name for s in subjects] if not args.subjects.strip().isdigit()
                                 else len(subjects), motions, args.frames, vertices, seed=args.seed,
                                 fps=args.fps, force=args.force, on_sequence=done, tempo=args.tempo,
                                 parts=parts)
    elapsed = time.perf_counter() - start
    print(f"wrote {path}: {total} sequences ({len(subjects)} subjects x {len(motions)} motions) x "
          f"{args.frames} frames in {elapsed:.1f} s; read one as {path}:{subjects[0].name}_{motions[0]}")
    return 0

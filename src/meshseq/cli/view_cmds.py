"""meshseq commands to look at sequences: ``render`` (PNG film strip, GIF, MP4), ``export`` (.glb
animation, USD, MDD/PC2 point caches, or .npz / mesh folders) and ``view`` (interactive web viewer)."""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from meshseq.errors import MeshseqError

SEQ_HELP = ("a mesh sequence: folder of OBJ/PLY/OFF frames, .npz, FILE.h5:SEQUENCE, .glb/.gltf, "
            ".usd/.usda/.usdc, or an .mdd/.pc2 point cache (BASE.obj:CACHE.pc2)")
EXPORT_SUFFIXES = (".glb", ".npz", ".obj", ".ply", ".usd", ".usda", ".usdc", ".mdd", ".pc2")
DEFAULT_FPS = 24.0


def register(sub) -> None:
    """Add this module's sub-commands to the ``meshseq`` parser's ``sub`` (argparse subparsers)."""
    p = sub.add_parser(
        "render",
        help="render sequences to a PNG film strip, a GIF or an MP4 (offscreen, no GPU needed)",
        description="Render mesh sequences offscreen with a fixed camera framing all of them. "
        "OUT.png: a labelled film strip (rows = sequences, columns = frames). OUT.gif / OUT.mp4: "
        "the sequences side by side, animated. With --error-against GT, the ground truth comes "
        "first and every SEQ is coloured by its per-vertex distance to GT, with a colour bar.",
    )
    p.add_argument("seqs", nargs="+", metavar="SEQ", help=SEQ_HELP + "; several are shown together "
                   "and must share one mesh connectivity")
    p.add_argument("-o", "--output", required=True, metavar="OUT", help="output file: .png, .gif or .mp4")
    p.add_argument("--every", type=int, default=None, metavar="K",
                   help="show every K-th frame (default: PNG at most 8 columns, GIF/MP4 every frame)")
    p.add_argument("--frames", default=None, metavar="START:STOP",
                   help="only frames START..STOP-1 of every sequence (Python slice, e.g. 0:24 or 10:)")
    p.add_argument("--error-against", metavar="GT", default=None,
                   help="ground-truth sequence: colour each SEQ by its per-vertex error against GT")
    p.add_argument("--labels", default=None, metavar="A,B,...",
                   help="comma-separated row/column labels for the SEQs (default: their names)")
    p.add_argument("--fps", type=float, default=None,
                   help=f"frames per second of the sequence (default: the data's, else {DEFAULT_FPS:g}); "
                   "with --every K a GIF/MP4 plays at FPS/K so time runs at its true speed")
    p.add_argument("--height", type=int, default=None, metavar="PX",
                   help="height of one image tile in pixels (default: 200 for PNG, 240 for GIF/MP4)")
    p.add_argument("--up", default="y", help="the data's up axis: x, y, z, -x, -y or -z (default: y)")
    p.add_argument("--title", default=None, help="a title above a PNG film strip")
    p.add_argument("--renderer", choices=("auto", "pyrender", "matplotlib"), default="auto",
                   help="auto: pyrender on EGL where available, else matplotlib (slower) with a note")
    p.add_argument("--force", action="store_true", help="overwrite OUT if it exists")
    p.set_defaults(func=cmd_render)

    p = sub.add_parser(
        "export",
        help="export a sequence as glTF (.glb), USD, an MDD/PC2 point cache, .npz or a folder of frames",
        description="OUT.glb: glTF 2.0 binary, the first frame as the mesh and the others as morph "
        "targets played by an animation at --fps (opens as an animation in Blender and in browser "
        "glTF viewers). OUT.usd/.usda/.usdc: a USD stage with one Mesh whose points are sampled "
        "at every frame (time codes at --fps; upAxis from --up, y or z; --meters-per-unit). "
        "OUT.mdd / OUT.pc2: a point cache (float32 positions) plus the base mesh OUT.obj (frame 0 "
        "and the faces) for importers that apply a cache to an existing mesh. OUT.npz, or a "
        "folder path (OBJ frames; --format ply for binary PLY): the sequence as meshseq reads it back.",
    )
    p.add_argument("seq", metavar="SEQ", help=SEQ_HELP)
    p.add_argument("-o", "--output", required=True, metavar="OUT",
                   help="OUT.glb, OUT.usd(a/c), OUT.mdd, OUT.pc2, OUT.npz, or a folder (e.g. frames/)")
    p.add_argument("--fps", type=float, default=None,
                   help=f"frames per second of the animation (default: the data's, else {DEFAULT_FPS:g})")
    p.add_argument("--up", default="y", help="the data's up axis (glTF is y-up; a USD stage states y or z; default: y)")
    p.add_argument("--meters-per-unit", type=float, default=1.0, metavar="M",
                   help="USD only: the length of one data unit in meters, stated in the stage (default 1)")
    p.add_argument("--no-normals", action="store_true", help="leave vertex normals out of the .glb (smaller file)")
    p.add_argument("--format", choices=("obj", "ply"), default=None, help="frame format of a folder output")
    p.add_argument("--force", action="store_true", help="overwrite OUT if it exists")
    p.set_defaults(func=cmd_export)

    p = sub.add_parser(
        "view",
        help="play sequences side by side in a local web viewer",
        description="Start a web viewer on 127.0.0.1 (this machine only) that plays the sequences "
        "side by side with play/pause and a frame slider; open the printed address in a browser "
        "(over SSH: ssh -L PORT:127.0.0.1:PORT host). Runs until Ctrl-C.",
    )
    p.add_argument("seqs", nargs="+", metavar="SEQ", help=SEQ_HELP + "; several must share one connectivity")
    p.add_argument("--port", type=int, default=8080, help="port on 127.0.0.1 (default: 8080)")
    p.add_argument("--fps", type=float, default=None, help=f"playback speed (default: the data's, else {DEFAULT_FPS:g})")
    p.add_argument("--up", default="y", help="the data's up axis (default: y)")
    p.add_argument("--paused", action="store_true", help="start paused at frame 0")
    p.set_defaults(func=cmd_view)


def _load(spec: str):
    from meshseq.io import load_sequence

    return load_sequence(spec)


def _frame_slice(text: str | None) -> slice | None:
    """``"START:STOP"`` (either may be empty) -> a slice; None -> None."""
    if text is None:
        return None
    parts = text.split(":")
    try:
        if len(parts) != 2:
            raise ValueError
        start, stop = (int(p) if p.strip() else None for p in parts)
    except ValueError:
        raise MeshseqError(f"--frames {text!r}: expected START:STOP, e.g. 0:24") from None
    return slice(start, stop)


def _fps(args, seq) -> float:
    fps = args.fps if args.fps is not None else (seq.fps or DEFAULT_FPS)
    if not fps > 0:
        raise MeshseqError(f"--fps {fps}: must be positive")
    return float(fps)


def cmd_render(args: argparse.Namespace) -> int:
    from meshseq import render
    from meshseq.io import check_output

    suffix = render.check_output_suffix(args.output, render.IMAGE_SUFFIXES + render.ANIMATION_SUFFIXES)
    check_output(args.output, force=args.force)  # before loading or rendering anything
    if args.every is not None and args.every < 1:
        raise MeshseqError(f"--every {args.every}: must be at least 1")
    if args.height is not None and not 16 <= args.height <= 2048:
        raise MeshseqError(f"--height {args.height}: must be between 16 and 2048 pixels")
    render.up_vector(args.up)  # validate before loading
    window = _frame_slice(args.frames)
    seqs = [_load(s) for s in args.seqs]
    labels = [s.name for s in seqs]
    if args.labels is not None:
        labels = [s.strip() for s in args.labels.split(",")]
        if len(labels) != len(seqs):
            raise MeshseqError(f"--labels: {len(labels)} labels for {len(seqs)} sequences")
    gt = None
    if args.error_against is not None:
        gt = _load(args.error_against)
        render.check_same_connectivity([gt] + seqs)
    else:
        render.check_same_connectivity(seqs)
    first_frame = 0
    if window is not None:
        first_frame = window.indices(max(s.n_frames for s in seqs))[0]
        for s in seqs + ([gt] if gt is not None else []):
            kept = s.vertices[window]
            if kept.shape[0] == 0:
                raise MeshseqError(f"--frames {args.frames}: no frames of {s.name} ({s.n_frames} frames) in that range")
            s.vertices = kept
    gt_label = f"{gt.name} (ground truth)" if gt is not None else "ground truth"
    common = dict(
        labels=labels,
        ground_truth=None if gt is None else gt.vertices,
        ground_truth_label=gt_label,
        up=args.up,
        first_frame=first_frame,
        backend=args.renderer,
    )
    faces = seqs[0].faces
    if suffix == ".png":
        image = render.film_strip(
            [s.vertices for s in seqs], faces, every=args.every, tile_height=args.height or 200,
            title=args.title, **common,
        )
        render.save_image(args.output, image, force=args.force)
        print(f"wrote {args.output} ({image.shape[1]}x{image.shape[0]} film strip)")
    else:
        every = args.every or 1
        frames = render.animation_frames(
            [s.vertices for s in seqs], faces, every=every, tile_height=args.height or 240, **common
        )
        fps = _fps(args, seqs[0]) / every
        render.save_animation(args.output, frames, fps=fps, force=args.force)
        print(f"wrote {args.output} ({len(frames)} frames, {frames.shape[2]}x{frames.shape[1]}, {fps:g} fps)")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from meshseq.io import check_output

    out = args.output
    suffix = Path(out).suffix.lower()
    is_folder = out.endswith(("/", os.sep)) or suffix == "" or Path(out).is_dir()
    if not is_folder and suffix not in EXPORT_SUFFIXES:
        raise MeshseqError(f"{out}: unknown output extension {suffix!r}; expected "
                           f"{', '.join(EXPORT_SUFFIXES)} or a folder path")
    if args.format is not None and not is_folder:
        raise MeshseqError(f"--format {args.format}: only for a folder output, not {out}")
    check_output(out.rstrip("/" + os.sep) or out, force=args.force)  # with a cache's base mesh beside it
    if suffix in (".usd", ".usda", ".usdc"):
        from meshseq.formats.usd import _pxr

        _pxr()  # usd-core missing: say so before loading anything
        if args.up.lower().lstrip("+") not in ("y", "z"):
            raise MeshseqError(f"--up {args.up!r}: a USD stage's up axis is y or z")
    seq = _load(args.seq)
    if suffix == ".glb":
        from meshseq.export import save_glb

        fps = _fps(args, seq)
        save_glb(out, seq.vertices, seq.faces, force=args.force, fps=fps, name=seq.name,
                 normals=not args.no_normals, up=args.up)
        size = Path(out).stat().st_size
        print(f"wrote {out} ({seq.n_frames} frames as morph targets at {fps:g} fps, {size / 1e6:.1f} MB)")
    else:
        from meshseq.io import save_sequence

        if args.fps is not None or (suffix in (".usd", ".usda", ".usdc", ".mdd") and seq.fps is None):
            seq.fps = _fps(args, seq)
        save_sequence(seq, out, format=args.format, force=args.force, up=args.up,
                      meters_per_unit=args.meters_per_unit)
        base = Path(out).with_suffix(".obj")
        extra = {".mdd": f" at {seq.fps or 0:g} fps, base mesh {base}", ".pc2": f", base mesh {base}"}.get(suffix, "")
        if suffix in (".usd", ".usda", ".usdc"):
            extra = (f" as time samples at {seq.fps:g} fps, up axis {args.up.lstrip('+').upper()}, "
                     f"{args.meters_per_unit:g} m per unit")
        print(f"wrote {out} ({seq.n_frames} frames{extra})")
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    from meshseq.viewer import Viewer, check_port_free

    from meshseq.render import up_vector

    up_vector(args.up)  # bad options fail before the (slow) loading
    check_port_free("127.0.0.1", args.port)
    seqs = [_load(s) for s in args.seqs]
    viewer = Viewer(seqs, port=args.port, fps=_fps(args, seqs[0]), up=args.up, playing=not args.paused)
    try:
        print(f"meshseq view: open {viewer.url} in a browser (Ctrl-C to stop)", flush=True)
        while True:
            time.sleep(0.5)
    except KeyboardInterrupt:
        print("meshseq view: stopped", file=sys.stderr)
        return 0
    finally:
        viewer.stop()

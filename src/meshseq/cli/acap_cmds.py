"""meshseq commands of the feature layer: ``info``, ``features``, ``roundtrip``.

numpy and the library are imported inside the commands, so that ``meshseq --help`` stays fast.
"""

from __future__ import annotations

import argparse
import time

from meshseq.errors import MeshseqError

#: meshseq.acap.CONSISTENCY_MODES, kept here so that --help does not import torch (a test checks they agree)
CONSISTENCY_MODES = ("temporal-mst", "temporal", "spatial", "greedy")  # the first is the default


def register(sub) -> None:
    """Add ``info``, ``features`` and ``roundtrip`` to the ``meshseq`` parser's subparsers."""
    p = sub.add_parser("info", help="describe a mesh sequence (frames, vertices, faces, size, defects)",
                       description="Print frames, vertices, faces, bounding-box diagonal, connected "
                       "components, boundary / non-manifold edges and degenerate triangles of DATA.")
    p.add_argument("data", metavar="DATA", nargs="+",
                   help="the sequence (see `meshseq --help`; several mesh files are the frames of one "
                   "sequence), or several sequences (folders, .npz, ...): each is described, and --json "
                   "prints a list")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.add_argument("--no-jumps", dest="jumps", action="store_false",
                   help="skip the feature check (extracting the default ACAP features against frame 0 "
                   "and counting spurious 2 pi jumps of their rotation logs in time, and fast turns)")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("features", help="extract ACAP features (T, V, 9) to a .npz",
                       description="Extract ACAP deformation features of every frame against a "
                       "reference frame and write them with what reconstruction needs.")
    p.add_argument("data", metavar="DATA", nargs="+", help="the sequence (see `meshseq --help`)")
    p.add_argument("-o", "--output", required=True, metavar="OUT.npz", help="output file (.npz)")
    _feature_options(p)
    p.add_argument("--float32", action="store_true", help="store features as float32 (half the size)")
    p.add_argument("--force", action="store_true", help="overwrite OUT if it exists")
    p.add_argument("--json", action="store_true",
                   help="print a JSON summary (shape, options, spurious 2 pi jumps of the rotation logs: "
                   "steps longer than pi where the rotation changes by less than pi/2)")
    p.set_defaults(func=cmd_features)

    p = sub.add_parser("roundtrip", help="extract features, reconstruct, report the error and speed",
                       description="Extract ACAP features, reconstruct vertices from them, and compare "
                       "with the input: per-vertex error (after centroid alignment) relative to the "
                       "bounding-box diagonal, and frames per second of both directions.")
    p.add_argument("data", metavar="DATA", nargs="+", help="the sequence (see `meshseq --help`)")
    _feature_options(p)
    p.add_argument("--rigid", action="store_true",
                   help="also remove the best rotation (Kabsch) before measuring the error")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.set_defaults(func=cmd_roundtrip)


def _feature_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--consistency", choices=CONSISTENCY_MODES, default=CONSISTENCY_MODES[0],
                   help="rotation consistency: 'temporal-mst' (default; logs continuous in time with the "
                   "fewest spurious 2 pi jumps, the first frame walked along its smallest rotation "
                   "differences), 'temporal' (the same from a breadth-first walk), 'spatial' (per-frame BFS "
                   "of the reference code) or 'greedy' (each frame nearest the previous)")
    p.add_argument("--exact", action="store_true",
                   help="exact encoding: minimum-norm correction of the gradients so that "
                   "reconstruction returns the input (method.md 2.5)")
    p.add_argument("--reference-frame", type=int, default=0, metavar="K",
                   help="frame the features are taken against (default 0)")
    p.add_argument("--no-normal-row", dest="normal_row", action="store_false",
                   help="fit gradients without the normal term of the reference code")


def _load(args):
    from meshseq.io import load_sequence

    spec = args.data[0] if len(args.data) == 1 else args.data
    return load_sequence(spec)


def _reference(seq, k: int) -> np.ndarray:
    import numpy as np

    if not -seq.n_frames <= k < seq.n_frames:
        raise MeshseqError(f"--reference-frame {k} is out of range: {seq.source or seq.name} has "
                           f"{seq.n_frames} frames")
    if not np.ptp(seq.vertices[k], axis=0).any():
        raise MeshseqError(f"{seq.source or seq.name} frame {k % seq.n_frames}: all vertices are at one point; "
                           "ACAP features need a reference frame of non-zero size (--reference-frame)")
    from meshseq.acap.parts import check_reference_parts
    from meshseq.mesh import Topology

    check_reference_parts(seq.vertices[k], Topology.from_faces(seq.faces, seq.n_vertices),
                          f"{seq.source or seq.name} frame {k % seq.n_frames}")
    return seq.vertices[k]


def describe(seq) -> dict:
    """Summary numbers of a sequence (the ``info`` command's content)."""
    import numpy as np

    from meshseq.mesh import Topology, bounding_box_diagonal, degenerate_faces

    topo = Topology.from_faces(seq.faces, seq.n_vertices)
    return {
        "name": seq.name,
        "source": seq.source,
        "frames": seq.n_frames,
        "vertices": seq.n_vertices,
        "faces": seq.n_faces,
        "fps": seq.fps,
        "diag": bounding_box_diagonal(seq.vertices),
        "components": topo.n_components,
        "boundary_edges": topo.boundary_edge_count,
        "nonmanifold_edges": topo.nonmanifold_edge_count,
        "degenerate_faces": int(degenerate_faces(seq.vertices[0], seq.faces).sum()),
        "unreferenced_vertices_dropped": seq.vertex_map is not None,
        **({"smallest_part_vertices": int(np.bincount(topo.component_labels).min())} if topo.n_components > 1 else {}),
    }


def parts_note(info: dict) -> str | None:
    """What several parts mean for meshseq, one line (None for a mesh of one part)."""
    n = info["components"]
    if n <= 1:
        return None
    return (f"{info['source'] or info['name']}: {n} separate parts (connected components, the smallest "
            f"{info['smallest_part_vertices']} vertices): ACAP features carry each part's shape and rotation; "
            "where each part sits relative to the others is learned as three more channels per vertex")


def _sequences(args) -> list:
    """DATA of ``info``: several mesh files are the frames of one sequence; several whole
    sequences (folders, .npz, FILE.h5:NAME, ...) are one sequence each."""
    from meshseq.io import is_sequence_spec, load_sequence

    whole = [d for d in args.data if is_sequence_spec(d)]
    if len(args.data) == 1 or not whole:
        return [_load(args)]
    frames = [d for d in args.data if not is_sequence_spec(d)]
    if frames:
        raise MeshseqError(f"{frames[0]}: DATA mixes mesh files (the frames of one sequence) with whole "
                           f"sequences ({whole[0]}); give one or the other")
    return [load_sequence(d) for d in whole]


def cmd_info(args) -> int:
    from meshseq.io import json_text

    infos = []
    for seq in _sequences(args):
        info = describe(seq)
        if args.jumps:
            from meshseq.acap import extract
            from meshseq.acap.diagnostics import feature_jumps

            info["jump_check_consistency"] = CONSISTENCY_MODES[0]
            info.update(feature_jumps(extract(seq.vertices, seq.faces)))
        infos.append(info)
    if args.json and len(infos) > 1:
        print(json_text(infos))
    else:
        for info in infos:
            _print(info, args.json, "info" if len(infos) == 1 else f"info: {info['source']}")
            note = None if args.json else parts_note(info)
            if note:
                print(note)
    return 0


def cmd_features(args) -> int:
    from pathlib import Path

    import numpy as np

    from meshseq.acap import extract
    from meshseq.acap.parts import component_offsets
    from meshseq.io import atomic_output, check_output, json_text
    from meshseq.mesh import Topology

    out = Path(args.output)
    if out.suffix.lower() != ".npz":
        raise MeshseqError(f"{out}: -o/--output must end in .npz")
    check_output(out, force=args.force)
    seq = _load(args)
    ref = _reference(seq, args.reference_frame)
    feats = extract(seq.vertices, seq.faces, reference=ref, consistency=args.consistency,
                    normal_row=args.normal_row, exact=args.exact)
    topo = Topology.from_faces(seq.faces, seq.n_vertices)
    arrays = {
        "features": feats.astype(np.float32 if args.float32 else np.float64),
        "faces": seq.faces,
        "reference": ref,
        "component_offsets": component_offsets(seq.vertices, topo),
        "consistency": np.array(args.consistency),
        "exact": np.array(bool(args.exact)),
        "normal_row": np.array(bool(args.normal_row)),
    }
    with atomic_output(out, force=args.force) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
    from meshseq.acap.diagnostics import feature_jumps

    jumps = feature_jumps(feats)
    if args.json:
        print(json_text({"output": str(out), "frames": int(feats.shape[0]), "vertices": int(feats.shape[1]),
                         "consistency": args.consistency, "exact": bool(args.exact),
                         "reference_frame": args.reference_frame, **jumps}))
    else:
        print(f"wrote {out}: features {feats.shape} ({args.consistency} consistency"
              f"{', exact' if args.exact else ''}); {jumps['spurious_jumps']} spurious 2 pi jumps in time "
              f"on {jumps['spurious_jump_vertices']} vertices, largest step {jumps['largest_step']:.3g} rad")
    return 0


def roundtrip_report(seq, *, consistency=CONSISTENCY_MODES[0], exact=False, reference_frame=0,
                     normal_row=True, rigid=False) -> dict:
    """Extract, reconstruct, compare; the ``roundtrip`` command's numbers (see its help)."""
    import numpy as np

    from meshseq.acap import Reconstructor, extract, features_to_gradients
    from meshseq.acap.parts import component_offsets
    from meshseq.align import per_vertex_error
    from meshseq.mesh import Topology, bounding_box_diagonal

    v = seq.vertices
    ref = _reference(seq, reference_frame)
    t0 = time.perf_counter()
    feats = extract(v, seq.faces, reference=ref, consistency=consistency, normal_row=normal_row, exact=exact)
    t_extract = time.perf_counter() - t0
    offsets = component_offsets(v, Topology.from_faces(seq.faces, seq.n_vertices))
    t0 = time.perf_counter()
    recon = Reconstructor(ref, seq.faces)
    t_factor = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = recon.solve(feats, offsets=offsets, target=v)
    t_solve = time.perf_counter() - t0
    diag = bounding_box_diagonal(v)
    scale = 1.0 / diag if diag > 0 else np.nan  # a mesh of zero size has no relative error (JSON null)
    err = per_vertex_error(out, v) * scale
    report = {
        "name": seq.name,
        "frames": seq.n_frames,
        "vertices": seq.n_vertices,
        "diag": diag,
        "consistency": consistency,
        "exact": exact,
        "mean_error_rel": float(err.mean()),
        "max_error_rel": float(err.max()),
        "extract_fps": seq.n_frames / t_extract,
        "reconstruct_fps": seq.n_frames / t_solve,
        "factor_seconds": t_factor,
    }
    if rigid:
        report["mean_error_rel_rigid"] = float((per_vertex_error(out, v, rigid=True) * scale).mean())
    if recon.topology.n_components > 1:
        report.update(_parts_report(recon, feats, v, scale))
    if exact:
        plain = extract(v, seq.faces, reference=ref, consistency=consistency, normal_row=normal_row)
        g_plain, g_exact = features_to_gradients(plain), features_to_gradients(feats)
        report["gradient_change_rel"] = float(
            np.linalg.norm(g_exact - g_plain, axis=(-2, -1)).mean() / np.linalg.norm(g_plain, axis=(-2, -1)).mean())
        report["feature_change_rel"] = float(
            np.linalg.norm(feats - plain, axis=-1).mean() / np.linalg.norm(plain, axis=-1).mean())
    return report


def _parts_report(recon, feats, v, scale: float) -> dict:
    """A multi-part mesh's round trip without the true part offsets: ``mean_error_rel_from_features``
    as through a trained model (features scaled and stored as float32, the parts placed by their
    placement channels), and ``mean_error_rel_rest_placement``, every part at its rest offset (the
    nine ACAP channels alone)."""
    import numpy as np

    from meshseq.acap import Scaling
    from meshseq.align import per_vertex_error

    scaling = Scaling.fit(feats)
    through = scaling.invert(scaling.apply(feats).astype(np.float32).astype(np.float64))
    return {
        "parts": recon.topology.n_components,
        "mean_error_rel_from_features": float((per_vertex_error(recon.solve(through, target=v), v) * scale).mean()),
        "mean_error_rel_rest_placement": float(
            (per_vertex_error(recon.solve(feats[..., :9], target=v), v) * scale).mean()),
    }


def cmd_roundtrip(args) -> int:
    seq = _load(args)
    report = roundtrip_report(seq, consistency=args.consistency, exact=args.exact,
                              reference_frame=args.reference_frame, normal_row=args.normal_row,
                              rigid=args.rigid)
    _print(report, args.json, f"ACAP round trip: {seq.name}")
    return 0


def _print(values: dict, as_json: bool, title: str) -> None:
    if as_json:
        from meshseq.io import json_text

        print(json_text(values))
        return
    from rich.console import Console
    from rich.table import Table

    table = Table(show_header=False)
    for key, value in values.items():
        if isinstance(value, float):
            text = f"{value:.3g}" if abs(value) < 1e-2 or abs(value) >= 1e4 else f"{value:.4g}"
        else:
            text = str(value)
        table.add_row(key, text)
    console = Console()
    # the title on a line of its own, never wrapped: it may hold a long path (a table's title is
    # wrapped to the table's width, which cut the path in two)
    console.print(title, soft_wrap=True, markup=False, highlight=False)
    console.print(table)

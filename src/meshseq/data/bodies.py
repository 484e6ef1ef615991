"""Built-in human motion data: Anny bodies (many subjects x many motions) as mesh sequences.

Needs the optional extra ``bodies`` (``pip install 'meshseq[bodies]'``: the Anny body model,
https://github.com/naver/anny, Apache-2.0 code with CC0 MakeHuman data). Anny's first
construction on a machine takes a couple of minutes and writes about 790 MB to
``~/.cache/anny`` (``ANNY_CACHE_DIR`` moves it); afterwards it loads in under a second. No
network is used (``HF_HUB_OFFLINE=1`` is set unless you set it otherwise).

Pipeline for one sequence (``subject``, ``motion``):

1. :mod:`meshseq.data.motions` gives joint-rotation curves ``(T, 3, 3)`` per bone;
2. Anny poses the subject's body (phenotype: gender, age, muscle, weight, height, proportions)
   by linear blend skinning; only the body's skin is kept (its largest connected component,
   13,348 vertices, closed and manifold; the separate eyes and teeth are dropped);
3. :func:`ground` translates every frame so the feet rest on the floor ``z = 0`` without
   sliding (in-place motions keep both feet where they are; ``walk`` moves the body forward
   so the stance foot stays put; jumping jacks add a hop);
4. optionally the frames are carried to a fixed lower-resolution template (default 3,000
   vertices) by barycentric coordinates on the full mesh (:class:`Template`, made once by
   decimating the rest pose with libigl's QSlim), so every sequence shares one connectivity.

Coordinates are metres, ``+z`` up, the body faces ``-y``.
:func:`make_body_set` writes a Dyna-style HDF5 file (one dataset ``SUBJECT_MOTION`` of vertices
``(V, 3, T)`` per sequence, a shared ``faces``), readable as ``FILE.h5:SUBJECT_MOTION`` by
:func:`meshseq.io.load_sequence`; :func:`default_body_set` builds (once) and caches the small
set the demo uses.
"""

from __future__ import annotations

import functools
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from meshseq.data.accessories import attach, resolve_parts
from meshseq.data.motions import (MOTIONS, RIG_BONES, MotionParams, RigAxes, canonical_motion, motion_curves,
                                  varied_tempo)
from meshseq.errors import MeshseqError
from meshseq.io import MeshSequence, atomic_output, check_output

#: Phenotype parameters of Anny a subject sets (each in [0, 1]; gender 0 = male, 1 = female;
#: age 2/3 = young adult, 1 = old).
PHENOTYPES = ("gender", "age", "muscle", "weight", "height", "proportions")

#: Named subjects, like Dyna's: body types that differ in build, sex and age.
NAMED_SUBJECTS: dict[str, dict[str, float]] = {
    "female_fit": dict(gender=1.0, age=0.70, muscle=0.70, weight=0.40, height=0.55, proportions=0.5),
    "male_heavy": dict(gender=0.0, age=0.80, muscle=0.45, weight=1.00, height=0.40, proportions=0.5),
    "female_old": dict(gender=1.0, age=1.00, muscle=0.30, weight=0.65, height=0.35, proportions=0.5),
    "male_fit": dict(gender=0.0, age=0.70, muscle=0.85, weight=0.45, height=0.50, proportions=0.5),
    "female_heavy": dict(gender=1.0, age=0.75, muscle=0.35, weight=0.95, height=0.45, proportions=0.5),
    "male_slim": dict(gender=0.0, age=0.68, muscle=0.35, weight=0.10, height=0.60, proportions=0.4),
    "female_slim": dict(gender=1.0, age=0.67, muscle=0.45, weight=0.10, height=0.65, proportions=0.4),
    "male_old": dict(gender=0.0, age=1.00, muscle=0.30, weight=0.70, height=0.45, proportions=0.6),
}

DEFAULT_FPS = 30.0
DEFAULT_VERTICES = 3000
#: ``make-bodies --tempo``: a steady tempo, or holds, slow-downs and speed-ups.
TEMPOS = ("steady", "varied")
#: Frames Anny poses in one batch.
POSE_CHUNK = 64
#: Width (metres) of the smooth switch between the two feet as the floor contact.
CONTACT_SOFTNESS = 0.01

INSTALL_HINT = "pip install 'meshseq[bodies]'"


# ----------------------------------------------------------------------------------------------
# Subjects


@dataclass(frozen=True)
class Subject:
    """A body: ``name`` and Anny phenotype values (see :data:`PHENOTYPES`)."""

    name: str
    phenotype: dict

    def to_json(self) -> str:
        return json.dumps({k: round(float(v), 6) for k, v in self.phenotype.items()}, sort_keys=True)


def sample_subject(rng: np.random.Generator, name: str) -> Subject:
    """A random adult body (either sex, any build, young to old)."""
    return Subject(name, dict(
        gender=float(np.clip(rng.choice([0.0, 1.0]) + rng.normal(0.0, 0.08), 0.0, 1.0)),
        age=float(rng.uniform(0.62, 1.0)),
        muscle=float(rng.uniform(0.2, 0.9)),
        weight=float(rng.uniform(0.05, 1.0)),
        height=float(rng.uniform(0.15, 0.7)),
        proportions=float(rng.uniform(0.3, 0.7)),
    ))


def resolve_subjects(spec: int | str | Sequence[str], seed: int = 0) -> list[Subject]:
    """Subjects from a count (sampled from ``seed``: ``s00``, ``s01``, ...; subject ``i`` is the
    same whatever the count), or named ones (a list or a comma-separated string of names from
    :data:`NAMED_SUBJECTS`)."""
    if isinstance(spec, str) and spec.strip().isdigit():
        spec = int(spec)
    if isinstance(spec, (int, np.integer)):
        n = int(spec)
        if n < 1:
            raise MeshseqError(f"--subjects {n}: need at least 1 subject")
        return [sample_subject(np.random.default_rng([int(seed), 7919, i]), f"s{i:02d}") for i in range(n)]
    names = [s.strip() for s in (spec.split(",") if isinstance(spec, str) else spec) if s.strip()]
    if not names:
        raise MeshseqError("--subjects: give a count or subject names")
    out = []
    for name in names:
        if name not in NAMED_SUBJECTS:
            raise MeshseqError(f"--subjects: unknown subject {name!r} (a count, or names from: "
                               f"{', '.join(NAMED_SUBJECTS)})")
        out.append(Subject(name, dict(NAMED_SUBJECTS[name])))
    if len(set(names)) != len(names):
        raise MeshseqError(f"--subjects: a subject is named twice in {','.join(names)}")
    return out


def resolve_motions(spec: str | Sequence[str]) -> list[str]:
    """Motion names from a list or comma-separated string (``all`` = every built-in motion)."""
    names = [s.strip() for s in (spec.split(",") if isinstance(spec, str) else spec) if s.strip()]
    if names == ["all"]:
        return list(MOTIONS)
    if not names:
        raise MeshseqError("--motions: give at least one motion")
    out = []
    for name in names:
        key = canonical_motion(name)
        if key is None:
            raise MeshseqError(f"--motions: unknown motion {name!r} (known: {', '.join(MOTIONS)}, or all)")
        if key in out:
            raise MeshseqError(f"--motions: motion {key!r} is listed twice")
        out.append(key)
    return out


# ----------------------------------------------------------------------------------------------
# Anny


def _import_anny():
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    try:
        import anny  # noqa: F401
        import torch  # noqa: F401
    except ImportError as exc:
        raise MeshseqError(f"the Anny body model is not installed ({exc}); install the bodies extra: "
                           f"{INSTALL_HINT}") from None
    return anny


class BodyModel:
    """Anny's full body, restricted to its skin (largest connected component).

    Attributes:
        faces: ``(F, 3)`` int64 faces of the skin (13,348 vertices, 26,692 triangles).
        keep: ``(V,)`` indices of the skin's vertices among Anny's.
        soles: ``{"L": idx, "R": idx}`` skin vertices of each sole (the lowest 1.5 cm, in the
            rest pose, of the vertices skinned only to that foot and its toes, which move
            rigidly with the foot).
        rest: ``(V, 3)`` the default body's rest pose (the template is decimated from it).
    """

    def __init__(self, model):
        import torch

        self.model = model
        self.torch = torch
        labels = list(model.bone_labels)
        self.bone_index = {b: i for i, b in enumerate(labels)}
        self.n_bones = len(labels)
        faces = model.faces.detach().cpu().numpy().astype(np.int64)
        out = self._forward(None, {})
        full_rest = out["vertices"][0]
        from meshseq.mesh import Topology

        topo = Topology.from_faces(faces, full_rest.shape[0])
        counts = np.bincount(topo.component_labels)
        keep = np.flatnonzero(topo.component_labels == np.argmax(counts))
        remap = np.full(full_rest.shape[0], -1, dtype=np.int64)
        remap[keep] = np.arange(keep.size)
        f = remap[faces]
        self.faces = f[(f >= 0).all(axis=1)]
        self.keep = keep
        self.rest = full_rest[keep]
        # Sole vertices: skinned (almost) only to a foot and its toes, so they move rigidly
        # with the foot, and near the bottom of that foot.
        w = model.vertex_bone_weights.detach().cpu().numpy()[keep]
        bi = model.vertex_bone_indices.detach().cpu().numpy()[keep]
        self.soles = {}
        for side in ("L", "R"):
            bones = [i for b, i in self.bone_index.items() if b.endswith("." + side)
                     and (b.startswith("foot") or b.startswith("toe"))]
            foot = np.flatnonzero((w * np.isin(bi, bones)).sum(axis=1) > 0.98)
            z = self.rest[foot, 2]
            self.soles[side] = foot[z < z.min() + 0.015]
        heads = out["bone_heads"][0]
        self.rig = RigAxes.from_heads({b: heads[self.bone_index[b]] for b in RIG_BONES})

    @property
    def n_vertices(self) -> int:
        return int(self.keep.size)

    def _forward(self, phenotype: dict | None, rotations: dict[str, np.ndarray], n_frames: int = 1) -> dict:
        torch = self.torch
        pose = torch.eye(4, dtype=torch.float64).repeat(n_frames, self.n_bones, 1, 1)
        for bone, R in rotations.items():
            pose[:, self.bone_index[bone], :3, :3] = torch.as_tensor(np.asarray(R, dtype=np.float64))
        pheno = None if phenotype is None else {k: float(v) for k, v in phenotype.items()}
        with torch.no_grad():
            out = self.model(pose.to(self.model.dtype), phenotype_kwargs=pheno)
        return {"vertices": out["vertices"].detach().cpu().numpy().astype(np.float64),
                "bone_heads": out["bone_poses"][:, :, :3, 3].detach().cpu().numpy().astype(np.float64)}

    def rig_for(self, phenotype: dict | None) -> RigAxes:
        """Hinge axes and leg segments of the rest skeleton of the body ``phenotype``."""
        heads = self._forward(phenotype, {})["bone_heads"][0]
        return RigAxes.from_heads({b: heads[self.bone_index[b]] for b in RIG_BONES})

    def rest_for(self, phenotype: dict | None) -> np.ndarray:
        """Skin vertices ``(V, 3)`` of the body ``phenotype`` in its rest pose (not grounded)."""
        return self._forward(phenotype, {})["vertices"][0][self.keep]

    def pose(self, phenotype: dict, rotations: dict[str, np.ndarray], n_frames: int) -> np.ndarray:
        """Skin vertices ``(T, V, 3)`` of the body ``phenotype`` posed by ``rotations`` (bone ->
        ``(T, 3, 3)`` local-ref deltas), before grounding."""
        unknown = sorted(set(rotations) - set(self.bone_index))
        if unknown:
            raise ValueError(f"unknown Anny bones: {unknown}")
        out = np.empty((n_frames, self.n_vertices, 3))
        for start in range(0, n_frames, POSE_CHUNK):
            stop = min(start + POSE_CHUNK, n_frames)
            chunk = {b: R[start:stop] for b, R in rotations.items()}
            out[start:stop] = self._forward(phenotype, chunk, stop - start)["vertices"][:, self.keep]
        return out


@functools.lru_cache(maxsize=1)
def body_model() -> BodyModel:
    """Anny's body (built on first use: minutes and ~790 MB of cache on a new machine)."""
    anny = _import_anny()
    try:
        model = anny.Anny()
    except Exception as exc:  # construction failing (no cache and no data, disk full, ...)
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise MeshseqError(f"cannot build the Anny body model ({first}); its cache is "
                           f"{os.environ.get('ANNY_CACHE_DIR', '~/.cache/anny')}") from None
    return BodyModel(model)


# ----------------------------------------------------------------------------------------------
# Grounding


def ground(vertices: np.ndarray, soles: dict[str, np.ndarray], hop: np.ndarray | None = None,
           contact: np.ndarray | None = None) -> np.ndarray:
    """Translate each frame of ``vertices (T, V, 3)`` so the body stands on the floor ``z = 0``.

    The contact foot is the lower one (a smooth switch, :data:`CONTACT_SOFTNESS` wide, between
    the two); ``z`` puts its lowest sole point on the floor, plus ``hop (T,)``. Horizontally,
    without ``contact`` the feet's midpoint stays where it is at frame 0 (centred on the
    origin); with ``contact (T,)`` (walking: the weight of the left foot as the stance foot)
    each frame moves the body by the opposite of the stance foot's motion, so the stance foot
    does not slide and the body walks forward.
    """
    v = np.asarray(vertices, dtype=np.float64)
    zl = v[:, soles["L"], 2].min(axis=1)
    zr = v[:, soles["R"], 2].min(axis=1)
    al = v[:, soles["L"], :2].mean(axis=1)
    ar = v[:, soles["R"], :2].mean(axis=1)
    w = 0.5 * (1.0 + np.tanh((zr - zl) / CONTACT_SOFTNESS))  # weight of the left foot as contact
    z = -(w * zl + (1.0 - w) * zr)
    if hop is not None:
        z = z + hop
    if contact is not None:
        c = np.asarray(contact, dtype=np.float64)
        wm = 0.5 * (c[1:] + c[:-1])[:, None]
        step = wm * np.diff(al, axis=0) + (1.0 - wm) * np.diff(ar, axis=0)
        xy = -np.concatenate([np.zeros((1, 2)), np.cumsum(step, axis=0)])
    else:
        xy = -(0.5 * (al + ar) - 0.5 * (al[0] + ar[0]))
    xy = xy - 0.5 * (al[0] + ar[0])
    shift = np.concatenate([xy, z[:, None]], axis=1)
    return v + shift[:, None, :]


# ----------------------------------------------------------------------------------------------
# Lower-resolution template


@dataclass
class Template:
    """A fixed mesh embedded in the full skin: vertex ``i`` is the point with barycentric
    coordinates ``bary[i]`` in full-mesh triangle ``face_index[i]``.

    Attributes:
        faces: ``(F', 3)`` int64 triangles of the template.
        face_index: ``(V',)`` int64 triangle of the full mesh holding each template vertex.
        bary: ``(V',3)`` float64 barycentric coordinates (non-negative, sum 1).
        full_faces: ``(F, 3)`` the full mesh's triangles.
    """

    faces: np.ndarray
    face_index: np.ndarray
    bary: np.ndarray
    full_faces: np.ndarray

    @property
    def n_vertices(self) -> int:
        return int(self.face_index.size)

    def apply(self, vertices: np.ndarray) -> np.ndarray:
        """Template vertices ``(T, V', 3)`` of full-mesh frames ``(T, V, 3)``."""
        tri = np.asarray(vertices)[:, self.full_faces[self.face_index]]  # (T, V', 3, 3)
        return np.einsum("tnkc,nk->tnc", tri, self.bary)


def barycentric(points: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Barycentric coordinates ``(N, 3)`` of ``points (N, 3)`` in triangles ``a, b, c (N, 3)``
    (of the point's projection onto the triangle's plane), clipped to the triangle."""
    v0, v1, v2 = b - a, c - a, points - a
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
    den = np.where(np.abs(d00 * d11 - d01 * d01) > 0, d00 * d11 - d01 * d01, 1.0)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    out = np.clip(np.stack([1.0 - v - w, v, w], axis=1), 0.0, None)
    return out / out.sum(axis=1, keepdims=True)


#: Decimals (of a metre) the rest pose is rounded to before decimation (see ``make_template``).
TEMPLATE_DECIMALS = 7


def make_template(rest: np.ndarray, faces: np.ndarray, n_vertices: int) -> Template:
    """Decimate the closed genus-0 mesh ``rest (V, 3)``, ``faces (F, 3)`` to ``n_vertices`` with
    QSlim (libigl) and embed each decimated vertex at its closest point on the full mesh."""
    import igl

    # QSlim's collapse order turns on the last bits of the input, and Anny's rest pose differs in
    # them with torch's thread count (4e-16): rounded to 0.1 micrometre, the template (and so the
    # connectivity of every file make-bodies writes) no longer depends on it.
    rest = np.round(np.asarray(rest, dtype=np.float64), TEMPLATE_DECIMALS)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    n = int(n_vertices)
    if n < 100:
        raise MeshseqError(f"--vertices {n}: too few for a body (at least 100)")
    target_faces = 2 * n - 4  # closed genus 0: F = 2 V - 4
    out = igl.qslim(rest, faces, target_faces)
    U, G = np.asarray(out[0], dtype=np.float64), np.asarray(out[1], dtype=np.int64)
    _, fi, closest = igl.point_mesh_squared_distance(U, rest, faces)
    fi = np.asarray(fi, dtype=np.int64).ravel()
    tri = rest[faces[fi]]
    bary = barycentric(np.asarray(closest), tri[:, 0], tri[:, 1], tri[:, 2])
    return Template(faces=G, face_index=fi, bary=bary, full_faces=faces)


@functools.lru_cache(maxsize=4)
def body_template(n_vertices: int) -> Template:
    """The template of ``n_vertices`` of Anny's default body (made once per process)."""
    body = body_model()
    return make_template(body.rest, body.faces, n_vertices)


# ----------------------------------------------------------------------------------------------
# Sequences and sets


def sequence_rng(seed: int, subject_index: int, motion: str) -> np.random.Generator:
    """The random stream of one (subject, motion) performance: independent of what else is made."""
    return np.random.default_rng([int(seed), int(subject_index), MOTIONS.index(motion)])


def generate(subject: Subject, motion: str, frames: int, *, params: MotionParams | None = None,
             vertices: int | None = DEFAULT_VERTICES, fps: float = DEFAULT_FPS,
             times: np.ndarray | None = None) -> MeshSequence:
    """One sequence: ``subject`` doing ``motion`` for ``frames`` frames.

    Args:
        params: the performance's speed / amplitude / phase (default: the motion's own).
        times: ``(frames,)`` the motion's time at each frame (a time warp:
            :func:`meshseq.data.motions.varied_tempo`); default a steady tempo.
        vertices: the template's vertex count, or None (or at least the skin's 13,348) for the
            full-resolution skin.
    Returns:
        A :class:`MeshSequence` named ``SUBJECT_MOTION`` (metres, z up, facing -y).
    """
    key = canonical_motion(motion)
    if key is None:
        raise MeshseqError(f"unknown motion {motion!r} (known: {', '.join(MOTIONS)})")
    if frames < 2:
        raise MeshseqError(f"--frames {frames}: need at least 2 frames")
    body = body_model()
    m = motion_curves(key, frames, fps=fps, params=params, rig=body.rig_for(subject.phenotype), times=times)
    v = body.pose(subject.phenotype, m.rotations, frames)
    v = ground(v, body.soles, hop=m.hop, contact=m.contact if m.travels else None)
    faces = body.faces
    if vertices is not None and int(vertices) < body.n_vertices:
        tpl = body_template(int(vertices))
        v, faces = tpl.apply(v), tpl.faces
    return MeshSequence(vertices=v, faces=faces, name=f"{subject.name}_{key}", fps=fps)


def make_body_set(path: str | os.PathLike, subjects: int | str | Sequence[str] = 3,
                  motions: str | Sequence[str] = ("walk", "jumping_jacks", "punch"), frames: int = 64,
                  vertices: int | None = DEFAULT_VERTICES, seed: int = 0, fps: float = DEFAULT_FPS,
                  force: bool = False, tempo: str = "steady",
                  on_sequence: Callable[[str], None] | None = None, parts: Sequence[str] = ()) -> Path:
    """Write a Dyna-style HDF5 set of every subject doing every motion; returns its path.

    Layout: dataset ``faces`` ``(F, 3)`` int32 shared by all; one dataset ``SUBJECT_MOTION`` of
    vertices ``(V, 3, T)`` float32 per sequence, with attributes ``subject``, ``motion``,
    ``phenotype`` (JSON), ``speed``, ``amplitude``, ``phase``, ``fps``; file attributes say how it
    was made. ``tempo`` ``"varied"`` plays every performance with holds, slow-downs to a stop and
    speed-ups (:func:`meshseq.data.motions.varied_tempo`, drawn from its own stream, so the
    speed, amplitude and phase stay those of the steady set). Each performance's speed, amplitude and phase are drawn from ``seed``, the subject
    and the motion, so the same arguments give the same file. ``parts`` (names from
    :data:`meshseq.data.accessories.PARTS`) appends separate parts carried by each body, bound to
    the subject's rest pose (:func:`meshseq.data.accessories.attach`; file attributes
    ``parts`` and ``body_vertices`` say so). Written atomically;
    ``on_sequence(name)`` is called after each sequence (progress).
    """
    import h5py

    target = check_output(path, force=force)
    subs = resolve_subjects(subjects, seed=seed)
    mots = resolve_motions(motions)
    if int(frames) < 2:
        raise MeshseqError(f"--frames {frames}: need at least 2 frames")
    if tempo not in TEMPOS:
        raise MeshseqError(f"--tempo {tempo!r}: expected one of {', '.join(TEMPOS)}")
    parts = resolve_parts(parts)
    body = body_model()
    full = vertices is None or int(vertices) >= body.n_vertices
    with atomic_output(target, force=force) as tmp:
        with h5py.File(tmp, "w") as h5:
            faces = None
            for si, subject in enumerate(subs):
                for motion in mots:
                    params = MotionParams.sample(sequence_rng(seed, si, motion))
                    times = None if tempo == "steady" else varied_tempo(
                        int(frames), fps, np.random.default_rng([int(seed), si, MOTIONS.index(motion), 1]))
                    seq = generate(subject, motion, int(frames), params=params,
                                   vertices=None if full else int(vertices), fps=fps, times=times)
                    n_body = seq.vertices.shape[1]
                    if parts:
                        seq = _with_parts(seq, subject, None if full else int(vertices), parts)
                    if faces is None:
                        faces = seq.faces
                        h5.create_dataset("faces", data=faces.astype(np.int32))
                    ds = h5.create_dataset(seq.name, data=np.ascontiguousarray(
                        seq.vertices.transpose(1, 2, 0), dtype=np.float32))
                    ds.attrs.update(subject=subject.name, motion=motion, phenotype=subject.to_json(),
                                    speed=params.speed, amplitude=params.amplitude, phase=params.phase,
                                    fps=fps, tempo=tempo)
                    if times is not None:
                        ds.attrs["times"] = times
                    if on_sequence is not None:
                        on_sequence(seq.name)
            h5.attrs.update(generator="meshseq make-bodies (Anny body model)", seed=int(seed), fps=fps,
                            frames=int(frames), vertices=int(faces.max() + 1),
                            subjects=",".join(s.name for s in subs), motions=",".join(mots),
                            anny_version=_anny_version(), units="metres, z up, facing -y")
            if parts:
                h5.attrs.update(parts=",".join(parts), body_vertices=int(n_body))
    return target


def _with_parts(seq: MeshSequence, subject: Subject, vertices: int | None, parts: Sequence[str]) -> MeshSequence:
    """``seq`` with ``parts`` appended, bound to ``subject``'s rest pose (on the template of
    ``vertices``, or the full skin for None)."""
    rest = body_model().rest_for(subject.phenotype)
    if vertices is not None:
        rest = body_template(vertices).apply(rest[None])[0]
    v, f = attach(seq.vertices, seq.faces, rest, parts)
    return MeshSequence(vertices=v, faces=f, name=seq.name, fps=seq.fps)


def _anny_version() -> str:
    try:
        import importlib.metadata

        return importlib.metadata.version("anny")
    except Exception:
        return "unknown"


#: What :func:`default_body_set` builds.
DEFAULT_SET = dict(subjects=("female_fit", "male_heavy", "female_old"),
                   motions=("walk", "jumping_jacks", "punch"), frames=64, vertices=DEFAULT_VERTICES, seed=0)


def default_body_set(cache_dir: str | os.PathLike, on_sequence: Callable[[str], None] | None = None) -> Path:
    """The demo's default data: 3 subjects x 3 motions x 64 frames at 3,000 vertices, built on
    first use into ``cache_dir`` (about a minute once Anny is built) and reused afterwards."""
    d = DEFAULT_SET
    path = Path(cache_dir) / (f"anny_bodies_{len(d['subjects'])}x{len(d['motions'])}_f{d['frames']}"
                              f"_v{d['vertices']}_seed{d['seed']}.h5")
    if path.is_file():
        return path
    return make_body_set(path, subjects=list(d["subjects"]), motions=list(d["motions"]), frames=d["frames"],
                         vertices=d["vertices"], seed=d["seed"], on_sequence=on_sequence)

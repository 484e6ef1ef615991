"""Property-based tests (hypothesis) of everything meshseq reads: the mesh readers (OBJ, PLY,
OFF, NPZ, HDF5, MDD, PC2, glTF, USD) and the checkpoint loader.

Random bytes, truncations and overwritten or inserted bytes of valid files, and random arrays
(shapes, dtypes, values) give either a valid sequence or a one-line MeshseqError: never another
exception type, never a numpy RuntimeWarning, and never a file left behind.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import tempfile
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from conftest import torch_threads, training_data
from meshseq.errors import MeshseqError
from meshseq.io import MeshSequence, load_sequence

#: examples per property; MESHSEQ_FUZZ_EXAMPLES=2000 for a long hunt (random examples: a hunt);
#: the default run draws the same examples every time, so CI cannot fail by chance
EXAMPLES = int(os.environ.get("MESHSEQ_FUZZ_EXAMPLES", "40"))
FUZZ = settings(max_examples=EXAMPLES, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow],
                derandomize="MESHSEQ_FUZZ_EXAMPLES" not in os.environ)
FEW = settings(FUZZ, max_examples=max(1, EXAMPLES * 3 // 8))

OCTA_V = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float64)
OCTA_F = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
FRAMES = np.stack([OCTA_V * (1 + 0.1 * t) + 0.05 * t for t in range(3)])
#: tokens that readers trip over: huge and negative integers, special floats, separators
TOKENS = [b"99999999999999999999", b"-99999999999999999999", b"-1", b"0", b"3", b"nan", b"inf", b"1e308",
          b"1e200", b"-1e-320", b"\n", b" ", b"\x00", b"\xff", b"f", b"v", b"/", b"#", b"element", b"end_header"]


def _valid_files() -> dict[str, bytes]:
    """Bytes of a small valid file of every format meshseq reads (written by meshseq itself)."""
    from meshseq.formats.caches import mdd_bytes, pc2_bytes
    from meshseq.io import save_sequence

    seq = MeshSequence(FRAMES, OCTA_F, name="octa", fps=24.0)
    one = MeshSequence(FRAMES[:1], OCTA_F, name="octa")
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        save_sequence(one, tmp / "a.obj")
        save_sequence(one, tmp / "a.ply")
        save_sequence(seq, tmp / "a.npz")
        save_sequence(seq, tmp / "a.glb")
        save_sequence(seq, tmp / "a.usda")
        with h5py.File(tmp / "a.h5", "w") as h:
            h["faces"] = OCTA_F
            h["seq"] = np.transpose(FRAMES, (1, 2, 0))
        for name in ("a.obj", "a.ply", "a.npz", "a.glb", "a.usda", "a.h5"):
            out[name] = (tmp / name).read_bytes()
        save_sequence(one, tmp / "ascii.ply")  # binary; an ASCII PLY too:
    out["ascii.ply"] = (b"ply\nformat ascii 1.0\nelement vertex 6\nproperty float x\nproperty float y\n"
                        b"property float z\nelement face 8\nproperty list uchar int vertex_indices\nend_header\n"
                        + b"".join(b"%g %g %g\n" % tuple(v) for v in OCTA_V)
                        + b"".join(b"3 %d %d %d\n" % tuple(f) for f in OCTA_F))
    out["a.off"] = (b"OFF\n6 8 0\n" + b"".join(b"%g %g %g\n" % tuple(v) for v in OCTA_V)
                    + b"".join(b"3 %d %d %d\n" % tuple(f) for f in OCTA_F))
    out["a.mdd"] = mdd_bytes(FRAMES, 24.0)
    out["a.pc2"] = pc2_bytes(FRAMES)
    return out


VALID = _valid_files()


def damaged(valid: bytes):
    """Random bytes, a truncation, overwritten bytes, or an inserted token of ``valid``."""
    n = len(valid)
    return st.one_of(
        st.binary(max_size=200),
        st.integers(0, n - 1).map(lambda k: valid[:k]),
        st.tuples(st.integers(0, n - 1), st.binary(min_size=1, max_size=6)).map(
            lambda t: valid[:t[0]] + t[1] + valid[t[0] + len(t[1]):]),
        st.tuples(st.integers(0, n), st.sampled_from(TOKENS)).map(lambda t: valid[:t[0]] + t[1] + valid[t[0]:]),
    )


@pytest.fixture(scope="module")
def root():
    with tempfile.TemporaryDirectory() as tmp:
        yield Path(tmp)


def listing(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def loads_or_refuses(spec, root: Path):
    """load_sequence(spec) gives a valid sequence or a one-line MeshseqError; writes nothing."""
    before = listing(root)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            warnings.simplefilter("error", RuntimeWarning)  # overflow, invalid value: numbers gone wrong
            seq = load_sequence(spec)
    except MeshseqError as err:
        assert "\n" not in str(err) and str(err), repr(err)
        seq = None
    if seq is not None:
        assert np.isfinite(seq.vertices).all() and seq.vertices.ndim == 3 and seq.vertices.shape[2] == 3
        assert seq.faces.min() >= 0 and seq.faces.max() < seq.n_vertices
    assert listing(root) == before
    return seq


def test_the_valid_files_load(root):
    for name, data in VALID.items():
        (root / name).write_bytes(data)
        if name.endswith((".mdd", ".pc2")):
            (root / name).with_suffix(".obj").write_bytes(VALID["a.obj"])
        spec = f"{root / name}:seq" if name.endswith(".h5") else root / name
        assert loads_or_refuses(spec, root) is not None, name
        for p in root.iterdir():
            p.unlink()


@pytest.mark.parametrize("name", ["a.obj", "a.off", "a.ply", "ascii.ply", "a.npz", "a.glb", "a.mdd", "a.pc2"])
@FUZZ
@given(data=st.data())
def test_damaged_files_load_or_give_one_line_errors(name, data, root):
    content = data.draw(damaged(VALID[name]))
    path = root / name
    path.write_bytes(content)
    if name.endswith((".mdd", ".pc2")):  # the base mesh beside the cache
        path.with_suffix(".obj").write_bytes(VALID["a.obj"])
    loads_or_refuses(path, root)


@FEW
@given(content=damaged(VALID["a.h5"]), key=st.sampled_from(["seq", "faces", "", "x/y"]))
def test_damaged_hdf5_loads_or_gives_one_line_errors(content, key, root):
    (root / "a.h5").write_bytes(content)
    loads_or_refuses(f"{root / 'a.h5'}:{key}", root)


@FEW
@given(content=damaged(VALID["a.usda"]))
def test_damaged_usd_loads_or_gives_one_line_errors(content, root):
    pytest.importorskip("pxr")
    path = root / "a.usda"
    path.write_bytes(content)
    loads_or_refuses(path, root)


DTYPES = [np.float64, np.float32, np.float16, np.int64, np.int8, np.uint64, np.bool_, np.complex128]


def any_array(dtypes=DTYPES, max_dims=4):
    return st.sampled_from(dtypes).flatmap(lambda dt: hnp.arrays(
        dt, hnp.array_shapes(min_dims=0, max_dims=max_dims, min_side=0, max_side=4)))


def vertex_like():
    """Arrays of shape (T, V, 3) (mostly) with any dtype and values (NaN, inf, 1e300, ...)."""
    shaped = st.tuples(st.integers(1, 3), st.integers(1, 6), st.sampled_from(DTYPES)).flatmap(
        lambda t: hnp.arrays(t[2], (t[0], t[1], 3)))
    return st.one_of(shaped, any_array())


def face_like():
    shaped = st.tuples(st.integers(1, 8), st.sampled_from([np.int64, np.int32, np.uint64, np.int8])).flatmap(
        lambda t: hnp.arrays(t[1], (t[0], 3), elements=st.integers(-2 if np.dtype(t[1]).kind == "i" else 0, 7)))
    return st.one_of(st.just(OCTA_F), shaped, any_array())


@FUZZ
@given(vertices=vertex_like(), faces=face_like(), extra=st.dictionaries(
    st.sampled_from(["fps", "name", "vertex_map"]), any_array(DTYPES + ["<U3"], max_dims=2), max_size=3))
def test_npz_of_random_arrays_loads_or_gives_one_line_errors(vertices, faces, extra, root):
    buf = io.BytesIO()
    np.savez(buf, vertices=vertices, faces=faces, **extra)
    (root / "r.npz").write_bytes(buf.getvalue())
    loads_or_refuses(root / "r.npz", root)


@FEW
@given(vertices=vertex_like(), faces=face_like(), fps=st.one_of(st.none(), st.floats(), st.text("abc1.e", max_size=3)))
def test_hdf5_of_random_arrays_loads_or_gives_one_line_errors(vertices, faces, fps, root):
    path = root / "r.h5"
    with h5py.File(path, "w") as h:
        h["faces"] = faces
        h["seq"] = np.moveaxis(vertices, 0, -1) if vertices.ndim == 3 else vertices
        if fps is not None:
            h["seq"].attrs["fps"] = fps
    loads_or_refuses(f"{path}:seq", root)


# --------------------------------------------------------------------------------------------
# the checkpoint loader


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
    """One checkpoint folder of a 1-iteration model (a few kB of weights)."""
    from meshseq import checkpoint as ckpt
    from meshseq.data.synthetic import twisting_limb
    from meshseq.train import TrainConfig, train

    run = tmp_path_factory.mktemp("ckpt") / "run"
    with torch_threads(1):
        train(training_data(twisting_limb(frames=12, rings=4, segments=4)), run,
              TrainConfig(iterations=1, window=3, batch=2, holdout=0.0), {"latent": 4, "lstm_layers": 1},
              device="cpu", progress=False, log=None)
    return ckpt.latest_checkpoint(run)


CHECKPOINT_FILES = ["model.json", "model.safetensors", "state.json", "state.safetensors"]


@FUZZ
@given(data=st.data(), name=st.sampled_from(CHECKPOINT_FILES), rehash=st.booleans())
def test_damaged_checkpoint_loads_or_gives_one_line_errors(data, name, rehash, tiny_checkpoint):
    """Damaged files of a checkpoint: the loader (meshseq.checkpoint.load_folder, model and
    training state) returns or raises MeshseqError. ``rehash``: the SHA-256 in the JSON is updated to the damaged
    safetensors, so that the safetensors parser itself is reached."""
    import hashlib

    from meshseq import checkpoint as ckpt

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / tiny_checkpoint.name
        shutil.copytree(tiny_checkpoint, folder)
        content = data.draw(damaged((folder / name).read_bytes()))
        (folder / name).write_bytes(content)
        if rehash and name.endswith(".safetensors"):
            meta_path = folder / name.replace(".safetensors", ".json")
            meta = json.loads(meta_path.read_text())
            meta["sha256"] = hashlib.sha256(content).hexdigest()
            meta_path.write_text(json.dumps(meta))
        before = listing(Path(tmp))
        for with_state in (False, True):
            try:
                loaded = ckpt.load_folder(folder, with_state=with_state)
            except MeshseqError as err:
                assert "\n" not in str(err), repr(err)
            else:
                assert isinstance(loaded.meta, dict)
                assert not with_state or isinstance(loaded.state_tensors, dict)
        assert listing(Path(tmp)) == before

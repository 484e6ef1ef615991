"""Issue 13: a user's mistake is one line (``meshseq: error: ...``, exit 2) found before any work,
and leaves nothing behind. Outputs that cannot be written, train options checked before the run
folder is created, a checkpoint's stored fields named as such (not as options nobody gave)."""

from __future__ import annotations

import json
import shutil
import tempfile

import pytest

from conftest import torch_threads, training_data
from meshseq.cli import main
from meshseq.data.synthetic import twisting_limb
from meshseq.io import save_sequence


@pytest.fixture(scope="module")
def limb_npz(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "limb.npz"
    save_sequence(twisting_limb(frames=30, rings=8, segments=6), path)
    return path


def listing(folder):
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def one_line_error(capsys, argv, *fragments):
    assert main([str(a) for a in argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("meshseq: error: ") and err.count("\n") == 1 and "Traceback" not in err, err
    for fragment in fragments:
        assert fragment in err, err
    return err


# Every command that writes, with OUT where its output goes (a suffix it accepts). RUN and DATA
# need not exist: the output is checked first, before anything is loaded or computed.
WRITERS = {
    "features": ["features", "{data}", "-o", "{out}.npz"],
    "predict": ["predict", "{run}", "{data}", "-o", "{out}.npz"],
    "complete": ["complete", "{run}", "{data}", "--keyframes", "0,5", "-o", "{out}.npz"],
    "evaluate --json": ["evaluate", "{run}", "{data}", "--json", "{out}.json"],
    "evaluate --plots": ["evaluate", "{run}", "{data}", "--plots", "{out}"],
    "render": ["render", "{data}", "-o", "{out}.png"],
    "export": ["export", "{data}", "-o", "{out}.pc2"],
    "make-bodies": ["make-bodies", "-o", "{out}.h5"],
    "demo": ["demo", "-o", "{out}"],
    "train": ["train", "{data}", "--out", "{out}"],
}


@pytest.mark.parametrize("command", sorted(WRITERS))
@pytest.mark.parametrize("where", ["inside a file", "/proc", "read-only folder"])
def test_unwritable_output_is_one_line_before_any_work(command, where, limb_npz, tmp_path, capsys, monkeypatch):
    """Issue 13 (4): an output inside an existing file, under /proc or in a read-only folder
    failed with a traceback, and only after the whole computation."""
    (tmp_path / "notes.txt").write_text("not a folder")
    if where == "inside a file":
        out, blamed = tmp_path / "notes.txt" / "sub" / "out", "notes.txt is a file, not a folder"
    elif where == "/proc":
        out, blamed = "/proc/meshseq-test/out", "cannot write in /proc"
    else:  # root writes into a mode-555 folder anyway: a read-only file system is simulated
        out, blamed = tmp_path / "ro" / "out", "cannot write in"
        (tmp_path / "ro").mkdir()

        def read_only(*args, **kwargs):
            raise OSError(30, "Read-only file system")

        monkeypatch.setattr(tempfile, "mkstemp", read_only)
    before = listing(tmp_path)
    argv = [a.format(data=limb_npz, run=tmp_path / "no-run", out=out) for a in WRITERS[command]]
    err = one_line_error(capsys, argv, blamed)
    assert str(out) in err
    assert listing(tmp_path) == before


@pytest.mark.parametrize("option, config, fragment", [
    (["--window", "1"], "", "--window 1: a window needs at least 2 frames"),
    ([], "holdout = 1.0", "run.toml: holdout: 1.0: expected a fraction in [0, 1)"),
    (["--latent", "0"], "", "--latent 0: expected an integer of at least 1"),
    ([], "[model]\nlstm_layers = 0", "run.toml: model.lstm_layers: 0: expected an integer of at least 1"),
    ([], 'holdout_at = "xyz"', "run.toml: holdout_at: 'xyz'"),
    ([], 'holdout_at = "1.5"', "run.toml: holdout_at: '1.5'"),
    ([], "w_motion = -1", "run.toml: w_motion: loss weight w_motion=-1.0 must be >= 0"),
    ([], "w_motoin = 1", "run.toml: w_motoin: not a training option (did you mean w_motion?"),
    # needs the data (the default recipe's window_fit shortens a window that does not fit)
    (["--window", "100"], 'window_fit = "none"', "--window 100 --stride 1 needs 100 consecutive training frames"),
])
def test_train_option_errors_create_no_run_folder(option, config, fragment, limb_npz, tmp_path, capsys):
    """Issue 13 (4): these errors were found after RUN was created, leaving an empty folder."""
    if config:
        (tmp_path / "run.toml").write_text(config + "\n")
        option = option + ["--config", str(tmp_path / "run.toml")]
    one_line_error(capsys, ["train", limb_npz, "--out", tmp_path / "run", "--iterations", "1", "--no-progress",
                            *option], fragment)
    assert not (tmp_path / "run").exists()


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory, limb_npz):
    from meshseq.io import load_sequence
    from meshseq.train import TrainConfig, train

    run = tmp_path_factory.mktemp("run") / "run"
    with torch_threads(1):
        train(training_data(load_sequence(limb_npz)), run, TrainConfig(iterations=1, window=4, batch=2),
              {"latent": 8, "lstm_layers": 1}, device="cpu", progress=False, log=None)
    return run


@pytest.mark.parametrize("field, value, expected", [
    ("variant", "bidirectional", "stored field model.variant = 'bidirectional': expected one of bd, std-bd, uni"),
    ("conv_impl", "dense", "stored field model.conv_impl = 'dense': expected one of gather, sparse"),
    ("latent", "eight", 'model.latent: expected an integer, got "eight"'),  # the JSON type check
    ("step_scale", [1.0, -2.0], "stored field model.step_scale = [1.0, -2.0]: expected 9 positive numbers"),
])
def test_bad_value_stored_in_a_checkpoint_is_named_as_its_field(field, value, expected, tiny_run, limb_npz,
                                                                 tmp_path, capsys):
    """Issue 13 (6): a bad variant in a checkpoint was reported as "--variant", an option nobody gave."""
    import meshseq
    from meshseq.errors import MeshseqError

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    meta_path = next(run.glob("checkpoints/*/model.json"))
    meta = json.loads(meta_path.read_text())
    meta["model"][field] = value
    meta_path.write_text(json.dumps(meta))
    err = one_line_error(capsys, ["predict", run, limb_npz, "-o", tmp_path / "out.npz"],
                         f"{meta_path}: {expected}")
    assert "--" not in err.split(expected)[0]
    assert not (tmp_path / "out.npz").exists()
    with pytest.raises(MeshseqError, match=f"model.{field}"):
        meshseq.load(run)

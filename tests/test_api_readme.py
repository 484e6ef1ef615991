"""The README's Python example runs as written, and misuse of the API is one MeshseqError line."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from conftest import shared_file
from meshseq.errors import MeshseqError

README = Path(__file__).resolve().parent.parent / "README.md"


@pytest.fixture(scope="module")
def cow_run(tmp_path_factory):
    from meshseq.train import TrainConfig, load_training_data, train

    run = tmp_path_factory.mktemp("api") / "cow"
    train(load_training_data([str(shared_file("pcow.npz"))]), run,
          TrainConfig(iterations=2, window=8, batch=2, eval_every=0, checkpoint_every=0, log_every=0),
          model_options={"latent": 16, "lstm_layers": 1}, device="cpu", progress=False, log=lambda m: None)
    return run


def readme_example() -> str:
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert blocks, "README.md has no Python example"
    code = blocks[0]
    assert len(code.splitlines()) <= 20
    return code


def test_readme_python_example_runs(cow_run, capsys):
    code = readme_example()
    assert '"runs/cow"' in code and '"../shared/data/pcow.npz"' in code
    code = code.replace('"runs/cow"', repr(str(cow_run))).replace('"../shared/data/pcow.npz"',
                                                                   repr(str(shared_file("pcow.npz"))))
    exec(compile(code, "README.md", "exec"), {})
    shapes = capsys.readouterr().out.strip()
    assert shapes == "(103, 2904, 3) (4, 21, 2904, 3) (10, 2904, 9)"


def test_api_misuse_is_one_meshseq_error(cow_run):
    import meshseq
    from meshseq.io import load_sequence

    model = meshseq.load(cow_run)
    v = load_sequence(str(shared_file("pcow.npz"))).vertices
    x = model.features(v[:2])
    with pytest.raises(MeshseqError, match="takes vertices"):
        model.complete(x, 5)
    with pytest.raises(MeshseqError, match="vertices"):
        model.complete(v[:2, :100], 5)
    with pytest.raises(MeshseqError, match="frames must be"):
        model.predict(v[0], 5)
    with pytest.raises(MeshseqError, match="frames must be"):
        model.sample(x, 5)


def test_sampled_continuations_differ_and_repeat_with_the_seed(cow_run):
    import meshseq
    from meshseq.io import load_sequence

    model = meshseq.load(cow_run)
    v = load_sequence(str(shared_file("pcow.npz"))).vertices[100:102]
    a = model.sample(v, 6, samples=3, seed=1)
    assert a.shape == (3, 8, 2904, 3)
    assert np.array_equal(a[:, :2], np.repeat(v[None], 3, 0).astype(a.dtype))
    assert not np.allclose(a[0], a[1])
    assert np.array_equal(a, model.sample(v, 6, samples=3, seed=1))

"""Training the BD-LSTM, one module per concept (``meshseq.train`` re-exports their public names):

- ``config``: ``TrainConfig`` (every option documented), ``RECIPES``, ``--config FILE.toml``;
- ``data``: ``TrainingData``, ``load_training_data``, the windows an iteration trains on;
- ``losses``: the loss terms and ``WindowLoss``, the objective;
- ``optim``: Adam's groups, gradient norms and clipping, the weights' moving average;
- ``run``: processes (torchrun), the run folder, metrics, the progress bar;
- ``loop``: ``train``, the loop.

This package's ``__init__`` imports nothing, so ``meshseq.training.config`` can be imported
(by ``meshseq.checkpoint_schema``, ``meshseq.baselines``) without the loop.
"""

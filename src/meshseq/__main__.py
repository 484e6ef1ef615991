"""``python -m meshseq``: the same as the ``meshseq`` command."""

from meshseq.cli import run

run()

"""``meshseq --help`` and ``meshseq COMMAND --help`` import none of the heavy libraries.

The command line imports torch, numpy, scipy, ... inside the commands that use them, so that its
help answers at once (a check of the imports rather than of the time, which varies with the machine).
The choices the parsers list without importing the library are checked against the library's own.
"""

from __future__ import annotations

import json
import subprocess
import sys

#: imported by none of the parsers (each costs 0.1-1.5 s to import)
HEAVY = ("torch", "numpy", "scipy", "trimesh", "h5py", "rich", "safetensors", "cma")

#: run in a fresh interpreter: every --help, then the heavy modules it imported, as JSON
PROBE = r"""
import argparse, contextlib, io, json, sys
import meshseq.cli

parser = meshseq.cli.build_parser()
commands = sorted(next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices)
for argv in [["--help"]] + [[c, "--help"] for c in commands]:
    with contextlib.redirect_stdout(io.StringIO()) as out:
        try:
            meshseq.cli.main(argv)
        except SystemExit as e:
            assert e.code == 0, (argv, e.code)
    assert "usage: meshseq" in out.getvalue(), argv
heavy = sorted(m for m in sys.argv[1:] if m in sys.modules)
print(json.dumps({"commands": commands, "heavy": heavy}))
"""


def test_help_imports_no_heavy_library():
    proc = subprocess.run([sys.executable, "-c", PROBE, *HEAVY], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert {"train", "predict", "info", "export", "make-bodies"} <= set(report["commands"]), report["commands"]
    assert report["heavy"] == [], f"meshseq --help imported {report['heavy']}"


def test_console_script_help_imports_no_torch():
    """The installed ``meshseq`` entry point itself, as a user runs it (``-X importtime`` lists its imports)."""
    proc = subprocess.run([sys.executable, "-X", "importtime", "-c", "from meshseq.cli import run; run()",
                           "train", "--help"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "--iterations" in proc.stdout
    imported = {line.split("|")[-1].strip() for line in proc.stderr.splitlines() if line.startswith("import time:")}
    assert "meshseq.cli" in imported  # (the modules importlib.import_module loads are not listed)
    assert not imported & {"torch", "numpy"}, sorted(imported & {"torch", "numpy"})


def test_choices_listed_without_the_library_match_it():
    from meshseq import checkpoint_schema
    from meshseq.acap import CONSISTENCY_MODES, DEFAULT_CONSISTENCY
    from meshseq.cli import acap_cmds, bodies_cmds
    from meshseq.data.motions import MOTIONS
    from meshseq.train import TrainConfig

    assert acap_cmds.CONSISTENCY_MODES == CONSISTENCY_MODES == checkpoint_schema.CONSISTENCY_MODES
    assert TrainConfig.consistency == DEFAULT_CONSISTENCY == CONSISTENCY_MODES[0]  # the config keeps a copy
    assert bodies_cmds.MOTIONS == MOTIONS

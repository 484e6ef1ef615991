"""Another git revision's ``src/meshseq`` as the package ``meshseq_rev``, loadable beside this checkout's.

Its imports, its C++ operators' namespace (``torch.ops.meshseq_rev``) and its kernels' build folder
(``meshseq_rev_kernels-...``) are renamed, so both versions and both kernel builds live in one
process: what ``kernel_ab.py`` and ``iteration_ab.py`` compare, call by call or iteration by
iteration, on the same moment of this machine.
"""

from __future__ import annotations

import io
import re
import subprocess
import tarfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RENAMES = [  # the package, its operators' namespace and its build folder, in Python and C++ sources
    (r"\bfrom meshseq\b", "from meshseq_rev"),
    (r"\bimport meshseq\b", "import meshseq_rev"),
    (r"torch\.ops\.meshseq\b", "torch.ops.meshseq_rev"),
    (r"TORCH_LIBRARY(_FRAGMENT)?\(meshseq,", r"TORCH_LIBRARY\1(meshseq_rev,"),
    (r"\bmeshseq_kernels\b", "meshseq_rev_kernels"),
]


def copy_revision(rev: str, folder: Path) -> None:
    """``src/meshseq`` at git revision ``rev`` as the package ``folder/meshseq_rev`` (put ``folder``
    on ``sys.path`` to import it)."""
    tar = subprocess.run(["git", "archive", rev, "src/meshseq"], cwd=ROOT, check=True, capture_output=True).stdout
    with tarfile.open(fileobj=io.BytesIO(tar)) as t:
        t.extractall(folder, filter="data")
    package = folder / "meshseq_rev"
    (folder / "src" / "meshseq").rename(package)
    for path in package.rglob("*"):
        if path.suffix in (".py", ".cpp", ".h"):
            text = path.read_text()
            for pattern, repl in RENAMES:
                text = re.sub(pattern, repl, text)
            path.write_text(text)

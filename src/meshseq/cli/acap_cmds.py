"""meshseq commands: acap_cmds (filled in by its issue)."""

from meshseq.cli import app  # noqa: F401

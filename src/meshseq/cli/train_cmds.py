"""meshseq commands: train_cmds (filled in by its issue)."""


def register(sub) -> None:
    """Add this module's sub-commands to the ``meshseq`` parser's ``sub`` (argparse subparsers)."""

"""The package's log messages on the terminal, as plain lines.

The library logs what it does through module loggers (``logging.getLogger(__name__)``, all
under ``ttd3_jax``): the runner's status lines at INFO, notes about damaged or missing
files at WARNING.  The command lines call :func:`show_messages` once, so a user reads the
text alone, INFO on stdout and WARNING and above on stderr.  The runner's per-epoch
progress line is not a log message: it is printed on stdout.
"""

from __future__ import annotations

import logging
import sys

PACKAGE_LOGGER = "ttd3_jax"


class Console(logging.Handler):
    """Each message as its text alone: below WARNING on stdout, the rest on stderr (the
    streams looked up per message, so a redirection made later still applies)."""

    def __init__(self):
        super().__init__()
        self.setFormatter(logging.Formatter("%(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        stream = sys.stdout if record.levelno < logging.WARNING else sys.stderr
        try:
            stream.write(self.format(record) + "\n")
            stream.flush()
        except Exception:  # logging's own contract: a failing handler does not raise
            self.handleError(record)


def show_messages(level: int = logging.INFO) -> logging.Logger:
    """Show the package's messages of ``level`` and above on the terminal (idempotent).  They
    do not also go to the root logger, where absl's ``basicConfig`` (run when orbax is
    imported) would print them a second time, prefixed."""
    log = logging.getLogger(PACKAGE_LOGGER)
    if not any(isinstance(h, Console) for h in log.handlers):
        log.addHandler(Console())
    log.setLevel(level)
    log.propagate = False
    return log

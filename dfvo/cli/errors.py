"""How the command-line tools end on an expected error: one line on stderr, the traceback in the run's log file."""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import NoReturn

__all__ = ["EXPECTED_ERRORS", "report_error"]

# bad settings, data, checkpoints or folders, and missing optional extras: the user's to fix, not bugs
EXPECTED_ERRORS: tuple[type[BaseException], ...] = (ValueError, OSError, ImportError)


def _log_files() -> list[Path]:
    return [Path(h.baseFilename) for h in logging.getLogger().handlers if isinstance(h, logging.FileHandler)]


def report_error(tool: str, message: str, exc: BaseException | None = None, exit_code: int = 1) -> NoReturn:
    """Print ``tool: message`` (the message is one line, or one line per problem; plus where the log is) to stderr,
    write the
    message and the traceback of ``exc`` to the log files of the root logger (Hydra's job log), and exit.

    Under a Hydra multirun the error is raised again instead (the launcher reports the failed job)."""
    logs = _log_files()
    record = logging.LogRecord("dfvo", logging.ERROR, __file__, 0, "%s", (message,),
                               (type(exc), exc, exc.__traceback__) if exc is not None else None)
    for handler in logging.getLogger().handlers:
        if isinstance(handler, logging.FileHandler):
            handler.handle(record)
    if exc is not None and _in_multirun():
        raise exc
    text = message.strip() or (type(exc).__name__ if exc is not None else "failed")
    where = f" [log: {logs[0]}]" if logs else ""
    print(f"{tool}: {'error: ' if exit_code == 1 else ''}{text}{where}", file=sys.stderr, flush=True)
    sys.exit(exit_code)


def _in_multirun() -> bool:
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN

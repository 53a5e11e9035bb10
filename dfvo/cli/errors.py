"""How the command-line tools end on an expected error: one line on stderr, the traceback in the run's log file.

Expected errors are the user's to fix, not bugs: bad settings, data, checkpoints or folders (``ValueError``,
``OSError`` and their subclasses), a missing optional extra (``ImportError``), and a config Hydra cannot compose (an
unknown key, a wrong type, an unknown group option). Each ends with ``TOOL: error: MESSAGE [log: FILE]`` on stderr;
the log file (Hydra's job log, ``OUT/infer.log``) holds the message and the traceback. ``verbose=true`` on the
command line (or ``HYDRA_FULL_ERROR=1``) shows the traceback instead.
"""

from __future__ import annotations

import functools
import logging
import os
import sys
import time
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import NoReturn

__all__ = ["EXPECTED_ERRORS", "LOG_ATTRIBUTE", "report_error", "one_line", "run_reporting_errors",
           "argv_value", "argv_flag", "guard_log_files", "closest_key", "quoting_hint"]

# bad settings, data, checkpoints or folders, and missing optional extras: the user's to fix, not bugs
EXPECTED_ERRORS: tuple[type[BaseException], ...] = (ValueError, OSError, ImportError)
# an exception re-raised from a multirun job carries its job's log file here (survives the launcher's pickling)
LOG_ATTRIBUTE = "dfvo_log_file"
QUOTES = "'\""
_NOISE = ("to append to your config", "full_key:", "reference_type=", "object_type=", "config search path",
          "provider=", "set the environment variable hydra_full_error")


# log files that failed to be written (a full disk): path -> reason; their handlers are detached
_FAILED_LOGS: dict[str, str] = {}


def _log_files() -> list[Path]:
    return [Path(h.baseFilename) for h in logging.getLogger().handlers if isinstance(h, logging.FileHandler)]


def guard_log_files() -> None:
    """Make the root logger's log files fail quietly and once: a record that cannot be written (a full disk, a
    quota) detaches its file handler instead of printing logging's ``--- Logging error ---`` traceback for every
    record; the failure is named in the error line of :func:`report_error`. Call it once logging is configured
    (inside the Hydra task)."""
    for handler in logging.getLogger().handlers:
        if isinstance(handler, logging.FileHandler) and not getattr(handler, "_dfvo_guarded", False):
            handler._dfvo_guarded = True  # type: ignore[attr-defined]
            handler.handleError = functools.partial(_log_failed, handler)  # type: ignore[method-assign]


def _log_failed(handler: logging.FileHandler, record: logging.LogRecord) -> None:
    err = sys.exc_info()[1]
    reason = getattr(err, "strerror", None) or str(err) or type(err).__name__
    _FAILED_LOGS.setdefault(handler.baseFilename, reason)
    logging.getLogger().removeHandler(handler)
    try:
        handler.close()
    except Exception:  # noqa: BLE001 - its flush fails the same way; the handler is gone either way
        pass


def _where_logged(logs: list[Path]) -> str:
    if logs:
        return f" [log: {logs[0]}]"
    if _FAILED_LOGS:
        path, reason = next(iter(_FAILED_LOGS.items()))
        return f" [log: {path} could not be written: {reason}]"
    return ""


def report_error(tool: str, message: str, exc: BaseException | None = None, exit_code: int = 1) -> NoReturn:
    """Print ``tool: message`` (the message is one line, or one line per problem; plus where the log is) to stderr,
    write the message and the traceback of ``exc`` to the log files of the root logger (Hydra's job log), and exit.

    Under a Hydra multirun the error is raised again instead (the launcher reports the failed job; the job's log
    file rides along as the attribute :data:`LOG_ATTRIBUTE`)."""
    logs = _log_files()
    record = logging.LogRecord("dfvo", logging.ERROR, __file__, 0, "%s", (message,),
                               (type(exc), exc, exc.__traceback__) if exc is not None else None)
    for handler in list(logging.getLogger().handlers):  # a failing (guarded) handler removes itself
        if isinstance(handler, logging.FileHandler):
            handler.handle(record)
    if exc is not None and _in_multirun():
        if logs:
            setattr(exc, LOG_ATTRIBUTE, str(logs[0]))
        raise exc
    text = message.strip() or (type(exc).__name__ if exc is not None else "failed")
    where = _where_logged(_log_files())
    print(f"{tool}: {'error: ' if exit_code == 1 else ''}{text}{where}", file=sys.stderr, flush=True)
    sys.exit(exit_code)


def _in_multirun() -> bool:
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def one_line(exc: BaseException) -> str:
    """The message of ``exc`` on one line: Hydra's and OmegaConf's multi-line reports (the failing override, the
    reason, the available options) joined by ``; `` without their bookkeeping lines (``full_key``,
    ``object_type``, the config search path, the HYDRA_FULL_ERROR hint)."""
    texts = [str(exc)]
    cause = exc.__cause__
    if cause is not None and str(cause) and str(cause) not in texts[0]:
        texts.append(str(cause))
    parts: list[str] = []
    options: list[str] | None = None  # the indented items under "Available options in 'GROUP':"
    for line in "\n".join(texts).splitlines():
        text = line.strip()
        if options is not None and text and line[:1] in ("\t", " "):
            options.append(text)
            continue
        if options is not None:
            parts[-1] += ", ".join(options)
            options = None
        if not text or text.lower().startswith(_NOISE):
            continue
        if text.lower().startswith("available options in"):
            parts.append("a" + text[1:].rstrip(":") + ": ")
            options = []
            continue
        parts.append(text.rstrip("."))
    if options is not None:
        parts[-1] += ", ".join(options)
    closest = closest_key(exc)
    if closest is not None:
        parts.append(closest)
    return "; ".join(parts) or type(exc).__name__


def closest_key(exc: BaseException) -> str | None:
    """For an unknown config key (an OmegaConf key error, or a Hydra error caused by one): ``the closest valid key
    is 'KEY'`` (full name), or the valid keys at that level when none is close; None for other errors."""
    import difflib

    for err in (exc, exc.__cause__, exc.__context__):
        parent, key = getattr(err, "parent_node", None), getattr(err, "key", None)
        if parent is None or key is None or not hasattr(parent, "keys"):
            continue
        valid = [str(k) for k in parent.keys() if str(k) != "hydra"]
        if str(key) in valid:
            continue
        full = str(getattr(err, "full_key", None) or key)
        prefix = full[: -len(str(key))] if full.endswith(str(key)) else ""
        match = difflib.get_close_matches(str(key), valid, n=1, cutoff=0.6)
        if match:
            return f"the closest valid key is '{prefix}{match[0]}'"
        kind = parent.get("kind", None) if hasattr(parent, "get") else None
        if prefix == "data." and kind == "synthetic":  # a dataset's setting given without choosing the dataset
            return (f"data={kind} (the default, the built-in world) has no data.{key}: choose the dataset first, "
                    f"e.g. data=kitti_odom data.{key}=... (kinds: kitti_odom, kitti_raw, folder, video, euroc, tum, "
                    "stream)")
        listed = ", ".join(f"{prefix}{k}" for k in valid[:12]) + (", ..." if len(valid) > 12 else "")
        return f"no valid key is close; valid keys there: {listed}"
    return None


def quoting_hint(argv: Sequence[str]) -> str | None:
    """What went wrong with an override Hydra's lexer refused, when it is a quoting problem: a value with spaces
    that the shell split into two words, or a value with non-ASCII letters given unquoted. None otherwise."""
    for i, arg in enumerate(argv):
        if arg.startswith("-"):
            continue
        key, sep, value = arg.partition("=")
        if not sep and i > 0 and "=" in argv[i - 1] and not argv[i - 1].startswith("-"):
            k, _, v = argv[i - 1].partition("=")
            return (f"'{arg}' is not key=value: a value with spaces split by the shell? Quote the override for the "
                    f"shell and the value for Hydra: \"{k.lstrip('+~')}='{v.strip(QUOTES)} {arg}'\"")
        if sep and (not value.isascii() or " " in value.strip()) and value[:1] not in QUOTES:
            return (f"{key}={value}: a value with spaces or non-ASCII letters must be quoted for Hydra, inside the "
                    f"shell's quotes: \"{key.lstrip('+~')}='{value}'\"")
    return None


def argv_value(argv: Sequence[str], key: str) -> str | None:
    """The value of a ``key=value`` override in ``argv`` (the last one wins; quotes stripped), or None."""
    value = None
    for arg in argv:
        name, sep, rest = arg.partition("=")
        if sep and name.lstrip("+~") == key:
            value = rest.strip("'\"")
    return value


def argv_flag(argv: Sequence[str], key: str) -> bool:
    """Whether ``key=true`` (or ``1``, ``yes``, ``on``) is among the overrides of ``argv``."""
    value = argv_value(argv, key)
    return value is not None and value.lower() in ("true", "1", "yes", "on")


def _write_log(path: Path, message: str, exc: BaseException) -> Path | None:
    """Append the message and the traceback of ``exc`` to ``path`` (folders created); None when that fails."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        stamp = time.strftime("%Y-%m-%d %H:%M:%S")
        with path.open("a") as f:
            f.write(f"[{stamp}][dfvo][ERROR] - {message}\n")
            f.write("".join(traceback.format_exception(type(exc), exc, exc.__traceback__)))
    except OSError:
        return None
    return path


def _log_file_message(err: BaseException) -> str | None:
    """The one line of a log file that cannot be opened (a read-only ``out_dir``, ``infer.log`` a folder): Python's
    ``logging`` says only ``Unable to configure handler 'file'``, the cause names the file."""
    cause = err.__cause__
    if not (isinstance(err, ValueError) and str(err).startswith("Unable to configure handler")
            and isinstance(cause, OSError) and cause.filename):
        return None
    return (f"cannot write the log file {cause.filename}: {cause.strerror or cause}; pass out_dir= a writable "
            "folder")


def run_reporting_errors(tool: str | None, hydra_main: Callable[[], object], log_name: str | None,
                         argv: Sequence[str] | None = None, exit_code: int = 1) -> None:
    """Run a ``@hydra.main`` function so that an expected error that escapes it (a config Hydra cannot compose, or a
    multirun job's error) ends with one line on stderr and exit status 1, like the errors the task itself reports.

    Hydra prints such errors itself, on several lines (with a traceback for a failed multirun job); here Hydra is
    asked to raise them (``HYDRA_FULL_ERROR=1`` for this process) and they are reported on one line. The traceback
    goes to ``OUT/LOG_NAME`` when the command line sets ``out_dir=OUT`` (a failed run says in OUT what failed),
    or to the failed job's own log. ``verbose=true`` or a user's own ``HYDRA_FULL_ERROR`` keep the full traceback.

    An unknown key names the closest valid key (:func:`closest_key`); an override Hydra's lexer refuses because
    of a missing quote (a path with spaces or non-ASCII letters) says how to quote it (:func:`quoting_hint`).
    This is the one home of those messages for ``dfvo-infer``, ``dfvo-train`` and ``dfvo-eval``.

    Args:
        tool: the command's name for the message (``dfvo-infer``; None: the line starts with ``error:``).
        hydra_main: the decorated function (called without arguments; Hydra reads ``sys.argv``).
        log_name: the log file's name inside ``out_dir`` (``infer.log``; None: no log file).
        argv: the command line (default ``sys.argv[1:]``).
        exit_code: the exit status of such an error.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    if os.environ.get("HYDRA_FULL_ERROR") or argv_flag(argv, "verbose"):
        os.environ.setdefault("HYDRA_FULL_ERROR", "1")  # verbose: Hydra's complete traceback, not its summary
        hydra_main()
        return
    from hydra.errors import HydraException, OverrideParseException
    from omegaconf.errors import OmegaConfBaseException

    os.environ["HYDRA_FULL_ERROR"] = "1"  # Hydra raises instead of printing its own multi-line report
    try:
        hydra_main()
    except BrokenPipeError:  # stdout closed by the reader (``--cfg job | head``): end quietly, as shell tools do
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        sys.exit(1)
    except (HydraException, OmegaConfBaseException, *EXPECTED_ERRORS) as err:
        message = one_line(err) if isinstance(err, HydraException | OmegaConfBaseException) else str(err).strip()
        message = _log_file_message(err) or message
        if isinstance(err, OverrideParseException):
            hint = quoting_hint(argv)
            message = f"cannot parse the command line: {hint}" if hint else message
        log = getattr(err, LOG_ATTRIBUTE, None)
        if log is None and log_name is not None:
            out_dir = argv_value(argv, "out_dir")
            multirun = "-m" in argv or "--multirun" in argv
            if out_dir and not (multirun and "," in out_dir):
                log = _write_log(Path(out_dir) / log_name, message, err)
        where = f" [log: {log}]" if log else ""
        print(f"{tool + ': ' if tool else ''}error: {message}{where}", file=sys.stderr, flush=True)
        sys.exit(exit_code)

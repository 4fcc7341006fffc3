"""Structured logging shared by every process: one JSON object (or text line) per record on stderr.

Every line about a request carries its ``request_id`` and every line about a job its ``job_id``,
plus the ``request_id`` of the request that created the job, so that one id follows an upload
from the API into the worker that ran its comparison:

- the API's request-log middleware binds the request id for the request
  (:func:`bind_request_id`); services read it (:func:`current_request_id`) to store it on the
  job they create;
- a worker notes the request id of each job it claims (:func:`remember_job_request_id`) and
  binds the job it is running (:func:`bind_job`);
- :class:`LogContextFilter`, on every handler made here, adds whichever of ``request_id`` and
  ``job_id`` a record lacks.

``SCANDIFF_LOG_FORMAT=json`` (the default) or ``text`` picks :class:`JsonFormatter` or
:class:`TextFormatter`.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import threading
from collections import OrderedDict
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from datetime import UTC, datetime
from typing import Any, Literal

LogFormat = Literal["json", "text"]
LOG_FORMATS: tuple[LogFormat, ...] = ("json", "text")
DEFAULT_LOG_FORMAT: LogFormat = "json"

STANDARD_RECORD_FIELDS = frozenset(
    vars(logging.LogRecord("", 0, "", 0, "", None, None)).keys() | {"message", "asctime"}
)

REMEMBERED_JOBS = 1024
"""How many jobs' request ids a process keeps (a worker runs one job at a time)."""

_request_id: ContextVar[str | None] = ContextVar("scandiff_request_id", default=None)
_job_id: ContextVar[str | None] = ContextVar("scandiff_job_id", default=None)
_job_request_ids: OrderedDict[str, str] = OrderedDict()
_job_request_ids_lock = threading.Lock()


def current_request_id() -> str | None:
    """The id of the API request being served in this context (None outside a request)."""
    return _request_id.get()


@contextmanager
def bind_request_id(request_id: str) -> Iterator[None]:
    """Within the block, log records and new jobs carry ``request_id``."""
    token = _request_id.set(request_id)
    try:
        yield
    finally:
        _request_id.reset(token)


def bind_job(job_id: str | None) -> None:
    """Log records of this context carry ``job_id`` from now on (None: no job any more)."""
    _job_id.set(job_id)


def remember_job_request_id(job_id: str, request_id: str | None) -> None:
    """Note that job ``job_id`` was created by request ``request_id`` (for this process's logs)."""
    if not request_id:
        return
    with _job_request_ids_lock:
        _job_request_ids[job_id] = request_id
        _job_request_ids.move_to_end(job_id)
        while len(_job_request_ids) > REMEMBERED_JOBS:
            _job_request_ids.popitem(last=False)


def job_request_id(job_id: str | None) -> str | None:
    """The request id noted for ``job_id`` in this process, if any."""
    if not job_id:
        return None
    with _job_request_ids_lock:
        return _job_request_ids.get(job_id)


class LogContextFilter(logging.Filter):
    """Add the bound ``job_id`` and ``request_id`` to records that do not carry them."""

    def filter(self, record: logging.LogRecord) -> bool:
        """Enrich ``record`` (never drops it)."""
        job_id = getattr(record, "job_id", None) or _job_id.get()
        if job_id and getattr(record, "job_id", None) is None:
            record.job_id = job_id
        if getattr(record, "request_id", None) is None:
            request_id = _request_id.get() or job_request_id(job_id)
            if request_id:
                record.request_id = request_id
        return True


def _timestamp(record: logging.LogRecord) -> str:
    return datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds")


def _extra_fields(record: logging.LogRecord) -> dict[str, Any]:
    return {
        key: value
        for key, value in vars(record).items()
        if key not in STANDARD_RECORD_FIELDS and not key.startswith("_")
    }


class JsonFormatter(logging.Formatter):
    """Render a record as one JSON line: time, level, logger, message, pid and ``extra`` fields."""

    def format(self, record: logging.LogRecord) -> str:
        """The record as a single-line JSON object."""
        entry: dict[str, Any] = {
            "ts": _timestamp(record),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
            "pid": record.process or os.getpid(),
        }
        entry.update(_extra_fields(record))
        if record.exc_info:
            entry["exception"] = self.formatException(record.exc_info)
        return json.dumps(entry, default=str)


class TextFormatter(logging.Formatter):
    """Render a record for people: ``time level logger message key=value ...``."""

    def format(self, record: logging.LogRecord) -> str:
        """The record as one line (plus the traceback, if any)."""
        fields = " ".join(f"{key}={value}" for key, value in _extra_fields(record).items())
        line = f"{_timestamp(record)} {record.levelname} {record.name} {record.getMessage()}"
        line = f"{line} {fields}" if fields else line
        if record.exc_info:
            line = f"{line}\n{self.formatException(record.exc_info)}"
        return line


def parse_log_format(value: str) -> LogFormat:
    """``json`` or ``text`` (any case, surrounding blanks ignored); ValueError otherwise."""
    word = value.strip().lower()
    for log_format in LOG_FORMATS:
        if word == log_format:
            return log_format
    raise ValueError(f"log format must be one of {', '.join(LOG_FORMATS)}, got {value!r}")


def make_handler(log_format: str | None = None) -> logging.Handler:
    """A stderr handler in ``log_format`` (default: the settings') adding the log context."""
    if log_format is None:
        from app.config import get_settings  # same layer; read only when not told

        log_format = get_settings().log_format
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(
        TextFormatter() if parse_log_format(log_format) == "text" else JsonFormatter()
    )
    handler.addFilter(LogContextFilter())
    return handler


def configure_process_logging(level: str = "INFO", log_format: str | None = None) -> None:
    """Send every log record of this process to stderr at ``level`` in ``log_format``."""
    handler = make_handler(log_format)
    root = logging.getLogger()
    for existing in list(root.handlers):
        root.removeHandler(existing)
    root.addHandler(handler)
    root.setLevel(level.upper())

"""Logging of the service: plain text (the default) or one JSON object per line.

``PWLREG_LOG_FORMAT=json`` makes every record of the API process and of the worker processes one
JSON object on one line, with ``time`` (UTC, ISO 8601), ``level``, ``logger``, ``message`` and,
when the record concerns a job, ``job_id`` and ``client`` (passed by the log calls as
``extra={"job_id": ..., "client": ...}``, see :func:`job_extra`); an exception adds
``exception``. No log call is given an API key.
"""

from __future__ import annotations

import json
import logging
from datetime import UTC, datetime
from typing import Any

TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
CONTEXT_FIELDS = ("job_id", "client")
"""Attributes of a record copied into its JSON object when set."""


def job_extra(job_id: str, client: str | None = None) -> dict[str, Any]:
    """The ``extra`` of a log call about a job (``client`` only when known)."""
    extra: dict[str, Any] = {"job_id": job_id}
    if client is not None:
        extra["client"] = client
    return extra


class JsonFormatter(logging.Formatter):
    """One JSON object per record, on one line."""

    def format(self, record: logging.LogRecord) -> str:
        doc: dict[str, Any] = {
            "time": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds")
            .replace("+00:00", "Z"),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        for name in CONTEXT_FIELDS:
            value = getattr(record, name, None)
            if value is not None:
                doc[name] = value
        if record.exc_info:
            doc["exception"] = self.formatException(record.exc_info)
        if record.stack_info:
            doc["stack"] = self.formatStack(record.stack_info)
        return json.dumps(doc, ensure_ascii=False, default=str)


def configure_logging(level: int | str, log_format: str = "text") -> None:
    """Send every record of this process to stderr, as text or JSON (``log_format``),
    replacing the root logger's handlers."""
    handler = logging.StreamHandler()
    if log_format == "json":
        handler.setFormatter(JsonFormatter())
    else:
        handler.setFormatter(logging.Formatter(TEXT_FORMAT))
    logging.basicConfig(level=level, handlers=[handler], force=True)
    logging.captureWarnings(log_format == "json")  # warnings too are records, not raw text

"""Structured logging: one line per record, key=value text or JSON (``ANT_LOG_JSON=1``)."""

from __future__ import annotations

import json
import logging
import sys
import time


class _Json(logging.Formatter):
    def __init__(self, service: str, instance: str):
        super().__init__()
        self.service, self.instance = service, instance

    def format(self, record: logging.LogRecord) -> str:
        out = {
            "ts": round(record.created, 3), "level": record.levelname, "service": self.service,
            "instance": self.instance, "logger": record.name, "msg": record.getMessage(),
        }
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out)


class _Text(logging.Formatter):
    def __init__(self, service: str, instance: str):
        super().__init__()
        self.prefix = f"{service}/{instance}"

    def format(self, record: logging.LogRecord) -> str:
        ts = time.strftime("%H:%M:%S", time.localtime(record.created))
        line = f"{ts} {record.levelname:<7} {self.prefix} {record.name}: {record.getMessage()}"
        if record.exc_info:
            line += "\n" + self.formatException(record.exc_info)
        return line


def configure_logging(service: str, instance: str, level: str = "INFO", as_json: bool = False) -> None:
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_Json(service, instance) if as_json else _Text(service, instance))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())
    # zenoh's Rust logs go through its own logger; keep Python-side third parties quiet.
    for noisy in ("httpx", "httpcore", "urllib3"):
        logging.getLogger(noisy).setLevel(logging.WARNING)

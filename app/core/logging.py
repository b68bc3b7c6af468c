"""Logging set-up: rich console output for the CLI, plain lines for the server, and secrets
(tokens, tickets, Authorization headers) redacted from every log line."""

from __future__ import annotations

import logging
import re

from rich.logging import RichHandler


def configure_logging(level: str = "INFO", rich: bool = True) -> None:
    handler: logging.Handler = (
        RichHandler(show_path=False, rich_tracebacks=False) if rich else logging.StreamHandler()
    )
    if not rich:
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    logging.basicConfig(level=level, handlers=[handler], force=True)


# Secrets that reach log lines through URLs and headers: `?token=` (the viewer websocket),
# `?ticket=` / `?session=` (viewer tickets), the login cookie, `Authorization` headers.
_SECRET_PARAM = re.compile(r"(?i)\b(\w*token|ticket|session)=([^&\s\"'#;,)\]]+)")
_BEARER = re.compile(r"(?i)\b(bearer|basic)(\s+)[A-Za-z0-9._~+/=-]+")
_AUTHORIZATION = re.compile(
    r"(?i)\b(authorization['\"]?\s*+[:=,]\s*+(?:b(?=['\"]))?+['\"]?+)(?!(?:bearer|basic)\s)"
    r"[^\s\"',}\]]+"
)
REDACTED = "***"
REDACTED_LOGGERS = ("uvicorn", "uvicorn.access", "uvicorn.error", "websockets", "app")


def redact(text: str) -> str:
    """`text` with the values of token=, ticket=, session= and Authorization headers as ***."""
    text = _SECRET_PARAM.sub(rf"\1={REDACTED}", text)
    text = _BEARER.sub(rf"\1\2{REDACTED}", text)
    return _AUTHORIZATION.sub(rf"\1{REDACTED}", text)


class RedactSecrets(logging.Filter):
    """Rewrites a record's message and string arguments with `redact` (never drops a record).

    Arguments are redacted one by one, not merged into the message: uvicorn's access formatter
    unpacks them."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.msg, str):
            record.msg = redact(record.msg)
        if isinstance(record.args, dict):
            record.args = {k: _redact_value(v) for k, v in record.args.items()}
        elif record.args:
            record.args = tuple(_redact_value(v) for v in record.args)
        return True


def _redact_value(value: object) -> object:
    return redact(value) if isinstance(value, str) else value


_FILTER = RedactSecrets()


def install_redaction() -> None:
    """Put the filter on the loggers that write request lines (uvicorn's access and error
    loggers, websockets, the app's) and on every handler they or the root logger write to, so
    records from child loggers (`app.api.main`) pass it too. Idempotent; call it after the
    server configured its logging (that replaces handlers)."""
    loggers = [logging.getLogger(name) for name in REDACTED_LOGGERS]
    handlers = [h for logger in (*loggers, logging.getLogger()) for h in logger.handlers]
    if logging.lastResort is not None:
        handlers.append(logging.lastResort)
    for target in (*loggers, *handlers):
        if _FILTER not in target.filters:
            target.addFilter(_FILTER)

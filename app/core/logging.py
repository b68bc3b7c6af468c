"""Logging set-up: rich console output for the CLI, plain lines for the server."""

from __future__ import annotations

import logging

from rich.logging import RichHandler


def configure_logging(level: str = "INFO", rich: bool = True) -> None:
    handler: logging.Handler = (
        RichHandler(show_path=False, rich_tracebacks=False) if rich else logging.StreamHandler()
    )
    if not rich:
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    logging.basicConfig(level=level, handlers=[handler], force=True)

"""Process-wide logging set-up for entry points (services and CLI)."""

from __future__ import annotations

import logging
import os


def setup_logging(name: str) -> logging.Logger:
    """Configure the root logger once (level from SPLITTAG_LOG_LEVEL, default INFO)."""
    level = os.environ.get("SPLITTAG_LOG_LEVEL", "INFO").upper()
    logging.basicConfig(
        level=level,
        format=f"%(asctime)s.%(msecs)03d {name} %(levelname)s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
    )
    return logging.getLogger(name)

"""The warnings torchfit logs (``log.warning``: one ``warning`` line on the console), as tests
read them from pytest's ``caplog``."""
from __future__ import annotations

import logging
import re


def warned(caplog, pattern: str) -> list[str]:
    """Messages of the WARNING records in ``caplog`` that match ``pattern`` (``re.search``)."""
    return [r.getMessage() for r in caplog.records
            if r.levelno == logging.WARNING and re.search(pattern, r.getMessage())]

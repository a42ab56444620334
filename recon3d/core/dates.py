"""The date products are stamped with, when the input holds none."""

from __future__ import annotations

import datetime as _dt
import os

__all__ = ["today"]


def today() -> str:
    """Today's date (ISO ``YYYY-MM-DD``, UTC), or that of ``SOURCE_DATE_EPOCH`` when set
    (the reproducible-builds convention: a fixed date gives the same bytes on any day)."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH", "").strip()
    if epoch.isdigit():
        return _dt.datetime.fromtimestamp(int(epoch), _dt.timezone.utc).date().isoformat()
    return _dt.datetime.now(_dt.timezone.utc).date().isoformat()

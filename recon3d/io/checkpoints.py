"""Check points: a CSV with header ``x,y,z`` and optional ``id`` and ``kind``."""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from recon3d.errors import InputError
from recon3d.io import require_file

__all__ = ["CheckPoints", "read_checkpoints"]

KINDS = ("ground", "roof", "")


@dataclass
class CheckPoints:
    """Reference points measured independently of the product (survey, GNSS, stereo plotter).

    Attributes
    ----------
    xyz : (n, 3) float64
    ids : (n,) str
    kinds : (n,) str
        "ground", "roof" or "" (unknown: compared with the DSM only).
    """

    xyz: np.ndarray
    ids: np.ndarray
    kinds: np.ndarray

    def __len__(self) -> int:
        return len(self.xyz)


def read_checkpoints(path: str | Path) -> CheckPoints:
    """Read a check-point CSV; every bad row is reported with its line number."""
    path = require_file(path, "check points")
    try:
        with path.open(newline="", encoding="utf-8-sig") as f:
            rows = list(csv.DictReader(f))
            header = [h.strip().lower() for h in (rows[0].keys() if rows else [])]
    except (UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"{path}: not a readable CSV file ({exc})") from None
    if not rows:
        raise InputError(f"{path}: no check points (expected a header x,y,z and one row per point)")
    if not {"x", "y", "z"} <= set(header):
        raise InputError(f"{path}: header must contain x,y,z (found {','.join(header)})")
    xyz, ids, kinds = [], [], []
    for line, row in enumerate(rows, start=2):
        row = {(k or "").strip().lower(): (v or "").strip() for k, v in row.items()}
        try:
            p = [float(row["x"]), float(row["y"]), float(row["z"])]
        except ValueError:
            raise InputError(f"{path}, line {line}: x, y and z must be numbers") from None
        if not np.isfinite(p).all():
            raise InputError(f"{path}, line {line}: x, y and z must be finite")
        kind = row.get("kind", "").lower()
        if kind not in KINDS:
            raise InputError(f"{path}, line {line}: kind must be ground or roof, not {kind!r}")
        xyz.append(p)
        ids.append(row.get("id") or str(line - 1))
        kinds.append(kind)
    return CheckPoints(np.array(xyz), np.array(ids), np.array(kinds))

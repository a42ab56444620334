"""The :class:`AccuracyReport`: the accuracy table of one product against one reference."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

__all__ = ["HIST_EDGES", "AccuracyReport"]

#: Bin edges (m) of the error histograms in reports; errors beyond +-3 m fall in the end bins.
HIST_EDGES = np.linspace(-3.0, 3.0, 25)


@dataclass(frozen=True)
class AccuracyReport:
    """Height errors of a product against a reference (product minus reference).

    The columns are those of the classic DSM/DTM accuracy studies, plus NMAD
    (1.4826 x median absolute deviation from the median), which is robust to blunders.
    Values are in metres; ``within_1m`` and ``within_2m`` are percentages.
    """

    product: str
    reference: str
    n: int
    mean: float
    std: float
    rms: float
    max_abs: float
    nmad: float
    within_1m: float
    within_2m: float
    histogram: dict | None = None

    @classmethod
    def from_errors(
        cls, errors: np.ndarray, *, product: str, reference: str, metres_per_unit: float = 1.0
    ) -> AccuracyReport:
        """Build the table from (n,) height errors in CRS units; NaNs are left out.

        ``metres_per_unit`` converts errors to metres, so reports of data in feet are
        still in metres (the tolerances +-1 m and +-2 m are metric).
        """
        e = np.asarray(errors, dtype=np.float64) * metres_per_unit
        finite = np.isfinite(e)
        if not finite.all():
            e = e[finite]
        del finite
        if e.size == 0:
            nan = float("nan")
            return cls(product, reference, 0, nan, nan, nan, nan, nan, nan, nan)
        # one temporary of the errors' size at a time: millions of check points (a survey's
        # provider ground) would otherwise hold several copies at once
        counts, _ = np.histogram(np.clip(e, HIST_EDGES[0], HIST_EDGES[-1]), bins=HIST_EDGES)
        deviation = e - np.median(e)
        np.abs(deviation, out=deviation)
        nmad = float(1.4826 * np.median(deviation, overwrite_input=True))
        del deviation
        return cls(
            product=product,
            reference=reference,
            n=int(e.size),
            mean=float(e.mean()),
            std=float(e.std(ddof=1)) if e.size > 1 else 0.0,
            rms=float(np.sqrt(np.mean(e**2))),
            max_abs=float(np.abs([e.min(), e.max()]).max()),
            nmad=nmad,
            within_1m=float(100.0 * (np.count_nonzero((e >= -1.0) & (e <= 1.0)) / e.size)),
            within_2m=float(100.0 * (np.count_nonzero((e >= -2.0) & (e <= 2.0)) / e.size)),
            histogram={"edges_m": HIST_EDGES.tolist(), "counts": counts.tolist(), "clipped_to_range": True},
        )

    def to_dict(self) -> dict:
        """JSON-ready dict (NaN becomes None)."""
        return {k: (None if isinstance(v, float) and not np.isfinite(v) else v)
                for k, v in asdict(self).items()}

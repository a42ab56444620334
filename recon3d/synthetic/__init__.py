"""Procedural test cities with exact ground truth, rendered to aerial stereo pairs."""

from recon3d.synthetic.city import SyntheticCity, checkpoints, make_city, truth_dsm, truth_dtm

__all__ = ["SyntheticCity", "checkpoints", "make_city", "truth_dsm", "truth_dtm"]

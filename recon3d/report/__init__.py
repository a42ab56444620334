"""The run report: report.json (written by the pipeline) rendered as a self-contained report.html."""

from recon3d.report.html import write_report

__all__ = ["write_report"]

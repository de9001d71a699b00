"""Reproduction reports: tables and figures from a sweep's MLflow runs, beside the paper's numbers."""

from gns_bench.report.report import write_all_reports, write_overviews, write_report

__all__ = ["write_all_reports", "write_overviews", "write_report"]

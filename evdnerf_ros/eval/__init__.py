"""Evaluation: the paper's event-image metrics, figures and the error-against-run-time report."""

from .metrics import (PSNR_CAP_DB, brightness_align, event_metrics, mae, mse,
                      protocol_windows, psnr, quantize_log_change, ssim)
from .figures import markdown_table, plot_runs, read_metrics, run_report, side_by_side

__all__ = [
    "PSNR_CAP_DB", "psnr", "ssim", "mae", "mse", "quantize_log_change", "event_metrics",
    "protocol_windows", "brightness_align",
    "side_by_side", "read_metrics", "plot_runs", "markdown_table", "run_report",
]

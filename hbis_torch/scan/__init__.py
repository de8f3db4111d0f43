"""Sub-pixel scanning with the Risley pair: scan plans, their alignment error, motor steps and
coarse ROI pointing (paper sections 2.2, 2.3 and 3.2). See docs/scanning.md."""

from .alignment import (
    CONVENTIONS,
    axis_alignment_error,
    pixel_alignment_error,
    pixel_grid,
    scan_report,
)
from .plan import (
    METHODS,
    ScanPlan,
    check_h,
    check_phase_pair,
    phase_range_deg,
    plan_scan,
    scan_offsets,
    step_mm,
)

__all__ = [
    "CONVENTIONS",
    "METHODS",
    "ScanPlan",
    "axis_alignment_error",
    "check_h",
    "check_phase_pair",
    "phase_range_deg",
    "pixel_alignment_error",
    "pixel_grid",
    "plan_scan",
    "scan_offsets",
    "scan_report",
    "step_mm",
]

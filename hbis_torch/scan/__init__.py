"""Sub-pixel scanning with the Risley pair: scan plans, their alignment error, motor steps and
coarse ROI pointing (paper sections 2.2, 2.3 and 3.2). See docs/scanning.md."""

from hbis_torch.scan.alignment import (
    CONVENTIONS,
    axis_alignment_error,
    pixel_alignment_error,
    pixel_grid,
    scan_report,
)
from hbis_torch.scan.motor_steps import (
    landing_jacobian,
    phase_steps,
    quantise_phases,
    required_steps_per_deg,
    step_alignment_error,
)
from hbis_torch.scan.plan import (
    METHODS,
    ScanPlan,
    phase_range_deg,
    plan_scan,
    scan_offsets,
    step_mm,
)
from hbis_torch.scan.pointing import Pointing, point_axis, point_sequence

__all__ = [
    "CONVENTIONS",
    "METHODS",
    "Pointing",
    "ScanPlan",
    "axis_alignment_error",
    "landing_jacobian",
    "phase_steps",
    "phase_range_deg",
    "pixel_alignment_error",
    "pixel_grid",
    "plan_scan",
    "point_axis",
    "point_sequence",
    "quantise_phases",
    "required_steps_per_deg",
    "scan_offsets",
    "scan_report",
    "step_alignment_error",
    "step_mm",
]

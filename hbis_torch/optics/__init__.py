"""Exact vector ray tracing through the Risley pair, and per-pixel landing maps."""

from hbis_torch.optics.pixels import (
    landing_map,
    landing_map_interpolated,
    pinhole_landing,
    pixel_coordinates,
    pixel_rays,
    rays_at,
    sensor_position,
)
from hbis_torch.optics.risley import (
    RisleyTrace,
    axis_deviation,
    deviation_azimuth,
    exit_directions,
    land_on_plane,
    risley_normals,
    trace_back,
    trace_faces,
    trace_risley,
)
from hbis_torch.optics.snell import refract
from hbis_torch.optics.inverse import (  # noqa: E402 - after the forward model it inverts
    axis_landing,
    exact_inverse,
    max_deviation_deg,
    max_landing_radius_mm,
    paper_inverse,
    paper_norms,
    paraxial_inverse,
)

__all__ = [
    "axis_landing",
    "exact_inverse",
    "max_deviation_deg",
    "max_landing_radius_mm",
    "paper_inverse",
    "paper_norms",
    "paraxial_inverse",
    "RisleyTrace",
    "axis_deviation",
    "deviation_azimuth",
    "exit_directions",
    "land_on_plane",
    "landing_map",
    "landing_map_interpolated",
    "pinhole_landing",
    "pixel_coordinates",
    "pixel_rays",
    "rays_at",
    "sensor_position",
    "refract",
    "risley_normals",
    "trace_back",
    "trace_faces",
    "trace_risley",
]

"""Exact vector ray tracing through the Risley pair, per-pixel landing maps, and the sample
positions of a scan's frames on the reference frame's grid."""

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
from hbis_torch.optics.sample_geometry import (
    NodePositions,
    interpolate_displacements,
    interpolate_positions,
    landing_at,
    landing_on_grid,
    node_positions,
    sample_positions,
)

__all__ = [
    "axis_landing",
    "exact_inverse",
    "max_deviation_deg",
    "max_landing_radius_mm",
    "paper_inverse",
    "paper_norms",
    "paraxial_inverse",
    "NodePositions",
    "RisleyTrace",
    "axis_deviation",
    "deviation_azimuth",
    "exit_directions",
    "interpolate_displacements",
    "interpolate_positions",
    "land_on_plane",
    "landing_at",
    "landing_map",
    "landing_map_interpolated",
    "landing_on_grid",
    "node_positions",
    "pinhole_landing",
    "pixel_coordinates",
    "pixel_rays",
    "rays_at",
    "sensor_position",
    "refract",
    "risley_normals",
    "sample_positions",
    "trace_back",
    "trace_faces",
    "trace_risley",
]

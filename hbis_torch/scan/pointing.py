"""Coarse ROI pointing (paper section 2.3): turn the fovea's optical axis toward a direction.

The paper points with the first-order (paraxial) model, which is enough to put an object inside
the fovea; :func:`point_axis` does that, and with ``exact=True`` refines the phases with the exact
non-paraxial inverse so that the axis lands on the wanted direction to rounding. Moving from one
target to the next takes the shortest rotation: of the two solutions (prisms' relative angle
+delta or -delta), the one nearer the current phases, each phase within half a turn of its
current value. At the centre (no deviation) the azimuth is undefined and the common rotation of
the current phases is kept, so a pass through the centre causes no 180 degree jump.

Directions are (deviation Phi from +z, azimuth Theta from +x toward +y), degrees.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.optics import axis_deviation
from hbis_torch.optics.inverse import exact_inverse, paraxial_inverse


@dataclass
class Pointing:
    """Phases that point the axis, and where it really points.

    Attributes
    ----------
    phases_deg : Tensor, shape (F, 2)
        [phi1, phi2] per target, degrees.
    deviation_deg, azimuth_deg : Tensor, shape (F,)
        The exact deviation and azimuth of the axis at those phases.
    miss_deg : Tensor, shape (F,)
        Angle between the wanted and the reached axis direction, degrees.
    """

    phases_deg: Tensor
    deviation_deg: Tensor
    azimuth_deg: Tensor
    miss_deg: Tensor


def _unit(deviation_deg: Tensor, azimuth_deg: Tensor) -> Tensor:
    d, a = torch.deg2rad(deviation_deg), torch.deg2rad(azimuth_deg)
    return torch.stack((torch.sin(d) * torch.cos(a), torch.sin(d) * torch.sin(a), torch.cos(d)), -1)


def _check_directions(deviation_deg, azimuth_deg) -> tuple[Tensor, Tensor]:
    dev = torch.as_tensor(deviation_deg, dtype=torch.float64).reshape(-1)
    az = torch.as_tensor(azimuth_deg, dtype=torch.float64).reshape(-1)
    if dev.shape != az.shape or dev.numel() == 0:
        raise HbisInputError(
            f"need as many azimuths as deviations (and at least one), got {dev.numel()} and "
            f"{az.numel()}"
        )
    if not (torch.isfinite(dev).all() and torch.isfinite(az).all()):
        raise HbisInputError("pointing directions contain non-finite values (NaN or inf)")
    if bool((dev < 0).any()) or bool((dev >= 90).any()):
        raise HbisInputError("deviation angles must lie in [0, 90) degrees")
    return dev, az


def _solve(system: FoveaSystem, dev: Tensor, az: Tensor, current: Tensor, exact: bool) -> Tensor:
    phases = paraxial_inverse(system.prisms, dev, az, current)
    if exact:
        # Refine on the coarse answer's branch and turn: it is the current point of the search.
        radius = system.object_distance_mm * torch.tan(torch.deg2rad(dev))
        a = torch.deg2rad(az)
        targets = torch.stack((radius * torch.cos(a), radius * torch.sin(a)), -1)
        phases = exact_inverse(system, targets, phases)
    return phases


def point_axis(
    system: FoveaSystem, deviation_deg, azimuth_deg, current_deg=(0.0, 0.0), exact: bool = False
) -> Pointing:
    """Phases that point the axis at each wanted direction, each solved from ``current_deg``.

    Parameters
    ----------
    system : FoveaSystem
        Prisms (and object distance, used for the exact refinement).
    deviation_deg, azimuth_deg : float or Tensor, shape (F,)
        Wanted deviation and azimuth of the axis, degrees.
    current_deg : (float, float) or Tensor, shape (F, 2)
        Phases the prisms are at now.
    exact : bool
        Refine the paraxial answer with the exact inverse (miss below 1e-9 degree).

    Returns
    -------
    Pointing
    """
    dev, az = _check_directions(deviation_deg, azimuth_deg)
    current = torch.as_tensor(current_deg, dtype=torch.float64)
    phases = _solve(system, dev, az, current, exact)
    return _pointing(system, phases, dev, az)


def point_sequence(
    system: FoveaSystem, deviation_deg, azimuth_deg, start_deg=(0.0, 0.0), exact: bool = False
) -> Pointing:
    """Visit targets in order, each reached by the shortest rotation from the previous one.

    Unlike :func:`point_axis`, the phases are not wrapped to stay near the start: they are the
    motor positions along the path (a prism that keeps turning one way keeps counting up).
    """
    dev, az = _check_directions(deviation_deg, azimuth_deg)
    current = torch.as_tensor(start_deg, dtype=torch.float64)
    rows = []
    for k in range(dev.numel()):
        current = _solve(system, dev[k : k + 1], az[k : k + 1], current, exact)[0]
        rows.append(current)
    return _pointing(system, torch.stack(rows), dev, az)


def _pointing(system: FoveaSystem, phases: Tensor, dev: Tensor, az: Tensor) -> Pointing:
    reached_dev, reached_az = axis_deviation(phases[:, 0], phases[:, 1], system.prisms)
    wanted, reached = _unit(dev, az), _unit(reached_dev, reached_az)
    miss = torch.rad2deg(torch.atan2(torch.linalg.cross(wanted, reached).norm(dim=-1),
                                     (wanted * reached).sum(-1)))
    return Pointing(phases, reached_dev, reached_az, miss)

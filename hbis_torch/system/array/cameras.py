"""The 3 x 3 camera array: nine Table 1 cameras, the centre one (the fovea) behind the Risley pair.

Camera C_ij (i = row 1..3 from the top, j = column 1..3 from the left) is rotated by
``hbis_torch.system.array.geometry``'s rotation; C22 is the fovea and defines the frame. All cameras
are modelled with one common centre of projection (the pupil of the fovea), so a view of the
plane scene is exactly a homography of another view (the real prototype's baselines of a few
centimetres are neglected, as the paper's stitching by projective transforms does).

A view can be rendered binned: ``binning`` b gives a (rows // b, cols // b) image whose pixel
(j, i) is centred at full-sensor coordinates ((j + 0.5) b - 0.5, (i + 0.5) b - 0.5).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import torch
from torch import Tensor

from hbis_torch.system.array.geometry import array_rotations
from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.optics import exit_directions, land_on_plane, rays_at

#: Camera names in row-major order; index 4 is the fovea.
CAMERA_NAMES = tuple(f"C{r}{c}" for r in (1, 2, 3) for c in (1, 2, 3))
FOVEA = "C22"
FOVEA_INDEX = CAMERA_NAMES.index(FOVEA)
#: Opposed prisms leave the fovea's axis (and, with thin prisms, every ray) undeviated.
PARKED_PHASES_DEG = (0.0, 180.0)


def small_rotation(yaw_deg: float, pitch_deg: float, roll_deg: float) -> Tensor:
    """Rotation (3, 3) float64: roll about z, then pitch about x, then yaw about y."""
    a, b, c = (math.radians(x) for x in (yaw_deg, pitch_deg, roll_deg))
    ry = torch.tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]],
                      dtype=torch.float64)
    rx = torch.tensor([[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]],
                      dtype=torch.float64)
    rz = torch.tensor([[math.cos(c), -math.sin(c), 0], [math.sin(c), math.cos(c), 0], [0, 0, 1]],
                      dtype=torch.float64)
    return ry @ rx @ rz


def _design_rotations(varphi_h_deg: float, varphi_v_deg: float) -> Tensor:
    rot = array_rotations(varphi_h_deg, varphi_v_deg)
    return torch.stack([rot[(int(n[1]), int(n[2]))] for n in CAMERA_NAMES])


@dataclass(frozen=True)
class CameraArray:
    """Nine cameras and the Risley pair in front of the centre one.

    Attributes
    ----------
    system : FoveaSystem
        The Table 1 camera (shared by all nine), the prisms and the object distance.
    varphi_h_deg, varphi_v_deg : float
        Design inclinations of the side cameras' axes (the prototype: 15 and 10 deg).
    rotations : Tensor, shape (9, 3, 3), float64
        The cameras' actual orientations (columns: camera x, y, z in the fovea's frame), in
        ``CAMERA_NAMES`` order. Equal to the design unless assembly errors were added.
    """

    system: FoveaSystem = field(default_factory=FoveaSystem)
    varphi_h_deg: float = 15.0
    varphi_v_deg: float = 10.0
    rotations: Tensor | None = None

    def __post_init__(self) -> None:
        for name in ("varphi_h_deg", "varphi_v_deg"):
            value = float(getattr(self, name))
            if not math.isfinite(value) or not 0.0 <= value < 45.0:
                raise HbisInputError(f"{name} must lie in [0, 45) degrees, got {value!r}")
        if self.rotations is None:
            object.__setattr__(self, "rotations", self.design_rotations)
        elif tuple(self.rotations.shape) != (9, 3, 3) or not torch.isfinite(self.rotations).all():
            raise HbisInputError("rotations must be a finite (9, 3, 3) tensor")

    @property
    def design_rotations(self) -> Tensor:
        """Rotations (9, 3, 3) of the design (no assembly error)."""
        return _design_rotations(self.varphi_h_deg, self.varphi_v_deg)

    def with_assembly_errors(self, sigma_deg: float = 0.7, seed: int = 0) -> "CameraArray":
        """A copy whose eight side cameras are misaligned by random yaw, pitch and roll.

        The errors are normal with standard deviation ``sigma_deg`` (a 3D-printed frame like the
        prototype's is off by about a degree). The fovea stays the reference frame.
        """
        if not math.isfinite(sigma_deg) or sigma_deg < 0:
            raise HbisInputError(f"sigma_deg must be >= 0, got {sigma_deg!r}")
        gen = torch.Generator().manual_seed(int(seed))
        errors = torch.randn(9, 3, generator=gen, dtype=torch.float64) * sigma_deg
        errors[FOVEA_INDEX] = 0.0
        rotations = torch.stack(
            [r @ small_rotation(*(float(e) for e in err)) for r, err in zip(self.design_rotations, errors)]
        )
        return replace(self, rotations=rotations)

    def intrinsics(self, binning: int = 1) -> Tensor:
        """K (3, 3) float64 of one camera's (binned) pixel grid: pixel = K (x/z, y/z, 1)."""
        cam = self.system.camera
        f = cam.focal_length_mm / cam.pitch_mm / binning
        cu = ((cam.cols - 1) / 2 + 0.5) / binning - 0.5
        cv = ((cam.rows - 1) / 2 + 0.5) / binning - 0.5
        return torch.tensor([[f, 0.0, cu], [0.0, f, cv], [0.0, 0.0, 1.0]], dtype=torch.float64)

    def view_shape(self, binning: int = 1) -> tuple[int, int]:
        """(rows, cols) of a view binned by ``binning``."""
        cam = self.system.camera
        if int(binning) != binning or binning < 1 or binning > min(cam.rows, cam.cols):
            raise HbisInputError(f"binning must be a positive integer, got {binning!r}")
        return cam.rows // binning, cam.cols // binning

    def camera_rays(self, binning: int = 1, supersample: int = 1, dtype=torch.float64) -> Tensor:
        """Chief rays (H s, W s, 3) of a camera's (binned) pixels in its own frame.

        With ``supersample`` s > 1 each binned pixel is split into s x s equal cells and the
        rays go through the cells' centres (for box integration over the pixel).
        """
        rows, cols = self.view_shape(binning)
        if int(supersample) != supersample or supersample < 1:
            raise HbisInputError(f"supersample must be a positive integer, got {supersample!r}")
        step = binning / supersample
        u = (torch.arange(cols * supersample, dtype=dtype) + 0.5) * step - 0.5
        v = (torch.arange(rows * supersample, dtype=dtype) + 0.5) * step - 0.5
        return rays_at(self.system.camera, u[None, :], v[:, None])

    @staticmethod
    def index(name: str) -> int:
        if name not in CAMERA_NAMES:
            raise HbisInputError(f"no camera {name!r}; the array has {', '.join(CAMERA_NAMES)}")
        return CAMERA_NAMES.index(name)

    def view_points(self, name: str, binning: int = 1, phases_deg=PARKED_PHASES_DEG,
                    supersample: int = 1, dtype=torch.float64) -> Tensor:
        """Where each (binned) pixel of camera ``name`` looks on the scene plane, mm.

        Returns (H s, W s, 2) for ``supersample`` s (see :meth:`camera_rays`). The fovea's rays
        go through the Risley pair at ``phases_deg`` (exact trace); the others are rotated by
        their actual orientation. Rendering uses float32 (about 1e-5 pixel, see the tracer's
        tests); analysis keeps the float64 default.
        """
        rays = self.camera_rays(binning, supersample, dtype)
        if self.index(name) == FOVEA_INDEX:
            out = exit_directions(rays, float(phases_deg[0]), float(phases_deg[1]), self.system.prisms)
        else:
            out = rays @ self.rotations[self.index(name)].T.to(dtype)
        return land_on_plane(out, self.system.object_distance_mm)

    def footprint_mm(self, binning: int = 1) -> float:
        """Spacing on the plane of the centre camera's (binned) pixels, mm."""
        return self.system.object_pixel_mm * binning

"""Physical parameters of one HBIS camera and its Risley pair.

Defaults are the prototype of the paper (Table 1). Lengths are in millimetres unless a name says
otherwise (``pixel_pitch_um``, ``wavelength_nm``), angles in degrees.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

from hbis_torch.errors import HbisInputError


#: The most pixels a sensor side may have (sensors today have under 20,000).
MAX_SENSOR_SIDE = 65536


def _check_positive(name: str, value: float) -> None:
    if not math.isfinite(value) or value <= 0:
        raise HbisInputError(f"{name} must be a finite positive number, got {value!r}")


@dataclass(frozen=True)
class LensCalibration:
    """OpenCV's pinhole-plus-distortion model of a real lens (``cv2.calibrateCamera``'s output).

    A pixel (u, v) (0-based centres, as OpenCV counts them) sees along the ray (x, y, 1) whose
    distorted normalised coordinates are ((u - cx) / fx, (v - cy) / fy); the distortion model is
    OpenCV's: radial k1, k2, k3 (and the rational k4, k5, k6), tangential p1, p2.

    Attributes
    ----------
    fx, fy : float
        Focal length in pixels along u and v (K[0, 0], K[1, 1]).
    cx, cy : float
        Principal point in pixels (K[0, 2], K[1, 2]).
    distortion : tuple of float
        (k1, k2, p1, p2[, k3[, k4, k5, k6]]): 4, 5 or 8 coefficients, OpenCV's order.
    image_size : (cols, rows) or None
        Size of the images the calibration was made with (refused for another sensor size).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple = ()
    image_size: tuple | None = None

    def __post_init__(self) -> None:
        for name in ("fx", "fy"):
            _check_positive(name, float(getattr(self, name)))
        for name in ("cx", "cy"):
            if not math.isfinite(float(getattr(self, name))):
                raise HbisInputError(f"{name} must be finite, got {getattr(self, name)!r}")
        d = tuple(float(x) for x in self.distortion)
        if len(d) not in (0, 4, 5, 8) or not all(math.isfinite(x) for x in d):
            raise HbisInputError(f"distortion must be 4, 5 or 8 finite coefficients (k1, k2, p1, p2[, k3[, k4, "
                                 f"k5, k6]]), got {self.distortion!r}")
        object.__setattr__(self, "distortion", d + (0.0,) * (8 - len(d)) if d else ())
        if self.image_size is not None:
            size = tuple(int(x) for x in self.image_size)
            if len(size) != 2 or min(size) < 1:
                raise HbisInputError(f"image_size must be (cols, rows), got {self.image_size!r}")
            object.__setattr__(self, "image_size", size)

    def to_dict(self) -> dict:
        out = {"K": [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]],
               "distortion": list(self.distortion)}
        if self.image_size is not None:
            out["image_size"] = list(self.image_size)
        return out


@dataclass(frozen=True)
class Camera:
    """A pinhole camera with a pixel array (Table 1).

    Attributes
    ----------
    pixel_pitch_um : float
        Pixel pitch p in micrometres.
    rows, cols : int
        Sensor size M x N in pixels (rows along y, columns along x).
    focal_length_mm : float
        Focal length f' in millimetres.
    f_number : float
        Working F-number F = f'/D.
    wavelength_nm : float
        Wavelength used for diffraction, in nanometres.
    lens : LensCalibration or None
        A real lens's calibration (principal point, focal length in pixels, distortion); None is
        the ideal camera of docs/design.md section 1 (centred, undistorted, f' / p pixels).
    """

    pixel_pitch_um: float = 3.75
    rows: int = 960
    cols: int = 1280
    focal_length_mm: float = 12.0
    f_number: float = 1.4
    wavelength_nm: float = 550.0
    lens: LensCalibration | None = None

    def __post_init__(self) -> None:
        if self.lens is not None and not isinstance(self.lens, LensCalibration):
            raise HbisInputError(f"lens must be a LensCalibration or None, got {type(self.lens).__name__}")
        for name in ("pixel_pitch_um", "focal_length_mm", "f_number", "wavelength_nm"):
            _check_positive(name, float(getattr(self, name)))
        for name in ("rows", "cols"):
            value = getattr(self, name)
            try:
                whole = not isinstance(value, bool) and int(value) == value
            except (TypeError, ValueError, OverflowError):
                whole = False
            if not whole or not 1 <= value <= MAX_SENSOR_SIDE:
                raise HbisInputError(f"{name} must be an integer from 1 to {MAX_SENSOR_SIDE}, got {value!r}")

    @property
    def pitch_mm(self) -> float:
        return self.pixel_pitch_um * 1e-3

    @property
    def pupil_diameter_mm(self) -> float:
        return self.focal_length_mm / self.f_number

    @property
    def half_fov_h_deg(self) -> float:
        """theta_h: half of the horizontal field of view (to the sensor's outer edge)."""
        return math.degrees(math.atan(self.cols / 2 * self.pitch_mm / self.focal_length_mm))

    @property
    def half_fov_v_deg(self) -> float:
        """theta_v: half of the vertical field of view (to the sensor's outer edge)."""
        return math.degrees(math.atan(self.rows / 2 * self.pitch_mm / self.focal_length_mm))


@dataclass(frozen=True)
class Prisms:
    """Two identical wedge prisms (the Risley pair).

    Attributes
    ----------
    wedge_angle_deg : float
        Wedge angle alpha in degrees, 0 < alpha < 90.
    refractive_index : float
        Refractive index n > 1 at the working wavelength.
    """

    wedge_angle_deg: float = 4.0
    refractive_index: float = 1.5

    def __post_init__(self) -> None:
        a, n = float(self.wedge_angle_deg), float(self.refractive_index)
        if not math.isfinite(a) or not 0 < a < 90:
            raise HbisInputError(f"wedge angle must lie in (0, 90) degrees, got {a!r}")
        if not math.isfinite(n) or n <= 1:
            raise HbisInputError(f"refractive index must be a finite number > 1, got {n!r}")


@dataclass(frozen=True)
class FoveaSystem:
    """The fovea of an HBIS: a camera behind a Risley pair, looking at an object plane.

    Examples
    --------
    The defaults are the paper's Table 1; fields are changed by keyword (the class is frozen):

    >>> from hbis_torch import Camera, FoveaSystem, Prisms
    >>> system = FoveaSystem()
    >>> system.camera.rows, system.camera.cols, system.prisms.wedge_angle_deg
    (960, 1280, 4.0)
    >>> system.object_pixel_mm          # p v / f' = 3.75 um x 50 mm / 12 mm
    0.015625
    >>> FoveaSystem(camera=Camera(f_number=2.8), object_distance_mm=100.0).object_pixel_mm
    0.03125
    """

    camera: Camera = field(default_factory=Camera)
    prisms: Prisms = field(default_factory=Prisms)
    object_distance_mm: float = 50.0

    def __post_init__(self) -> None:
        _check_positive("object distance", float(self.object_distance_mm))

    @property
    def object_pixel_mm(self) -> float:
        """One sensor pixel projected onto the object plane, in mm (p * v / f')."""
        return self.camera.pitch_mm * self.object_distance_mm / self.camera.focal_length_mm

    def to_dict(self) -> dict:
        return asdict(self)

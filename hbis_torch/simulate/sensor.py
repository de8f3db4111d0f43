"""The sensor: pixel fill factor, defocus, shot and read noise, black level and quantisation.

Signal chain of one pixel, from the noise-free irradiance ``I`` in [0, 1] (1 fills the well):

    electrons  e  = Poisson(I * full_well_e) + Normal(0, read_noise_e)
    DN            = round(black_level_dn + e * gain),   gain = (2**bit_depth - 1 - black) / full_well_e
    stored        = clip(DN, 0, 2**bit_depth - 1)

so the mean of DN is ``black + I * (white - black)`` and its variance ``gain**2 (I full_well +
read_noise**2) + 1/12`` (the last term from rounding). With ``bit_depth=None`` frames are stored as
float32 ``clip(e / full_well, 0, 1)`` (no black level, no rounding). ``noise=False`` skips the
random terms; what is left is the deterministic mean, still quantised.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import Tensor

from hbis_torch.errors import HbisInputError


@dataclass(frozen=True)
class SensorModel:
    """Pixel aperture, focus and noise of the simulated sensor.

    Attributes
    ----------
    fill_factor : float
        Light-sensitive fraction of the pixel area, in (0, 1]; the aperture is a centred square
        of side sqrt(fill_factor) * pitch.
    defocus_um : float
        Axial distance of the sensor from best focus, micrometres (0: in focus).
    full_well_e : float
        Electrons at irradiance 1 (the full well).
    read_noise_e : float
        Standard deviation of the Gaussian read noise, electrons.
    black_level_dn : float
        Digital number of a black pixel (stored as the stack's ``black_level``).
    bit_depth : int or None
        ADC bits, 1..16 (uint8 frames up to 8 bits, uint16 above); None stores float32 in [0, 1].
    noise : bool
        False gives the noise-free (but still quantised) frames.
    """

    fill_factor: float = 1.0
    defocus_um: float = 0.0
    full_well_e: float = 10000.0
    read_noise_e: float = 2.0
    black_level_dn: float = 0.0
    bit_depth: int | None = 12
    noise: bool = True

    def __post_init__(self) -> None:
        if not (math.isfinite(self.fill_factor) and 0 < self.fill_factor <= 1):
            raise HbisInputError(f"fill factor must lie in (0, 1], got {self.fill_factor!r}")
        if not math.isfinite(self.defocus_um):
            raise HbisInputError(f"defocus must be finite, got {self.defocus_um!r}")
        if not (math.isfinite(self.full_well_e) and self.full_well_e > 0):
            raise HbisInputError(f"full well must be a positive number of electrons, got {self.full_well_e!r}")
        if not (math.isfinite(self.read_noise_e) and self.read_noise_e >= 0):
            raise HbisInputError(f"read noise must be >= 0 electrons, got {self.read_noise_e!r}")
        if self.bit_depth is not None:
            if isinstance(self.bit_depth, bool) or int(self.bit_depth) != self.bit_depth or not 1 <= self.bit_depth <= 16:
                raise HbisInputError(f"bit depth must be an integer from 1 to 16 or None, got {self.bit_depth!r}")
            white = 2 ** int(self.bit_depth) - 1
            if not (math.isfinite(self.black_level_dn) and 0 <= self.black_level_dn < white):
                raise HbisInputError(
                    f"black level must lie in [0, {white}) for {self.bit_depth} bits, got {self.black_level_dn!r}"
                )

    @property
    def dtype(self) -> np.dtype:
        """Storage type of the frames: uint8 up to 8 bits, uint16 up to 16, float32 for None."""
        if self.bit_depth is None:
            return np.dtype(np.float32)
        return np.dtype(np.uint8) if self.bit_depth <= 8 else np.dtype(np.uint16)

    @property
    def white_level(self) -> int | None:
        return None if self.bit_depth is None else 2 ** int(self.bit_depth) - 1

    @property
    def gain_dn_per_e(self) -> float | None:
        """Digital numbers per electron (None for float output)."""
        if self.bit_depth is None:
            return None
        return (self.white_level - self.black_level_dn) / self.full_well_e

    def to_dict(self) -> dict:
        return asdict(self)


def expose(irradiance: Tensor, sensor: SensorModel, generator: torch.Generator | None = None) -> np.ndarray:
    """Turn noise-free irradiance into stored frames through the sensor's signal chain.

    Parameters
    ----------
    irradiance : Tensor, shape (...)
        Values in [0, 1] (1 = full well); float32 or float64.
    sensor : SensorModel
    generator : torch.Generator or None
        Source of the shot and read noise (deterministic when seeded).

    Returns
    -------
    np.ndarray, shape (...)
        ``sensor.dtype`` (uint8, uint16 or float32 in [0, 1]).
    """
    if not bool(torch.isfinite(irradiance).all()):
        raise HbisInputError("irradiance contains NaN or infinite values")
    # float32 holds every electron count and DN exactly (< 2**24)
    signal = irradiance.float().clamp(0.0, 1.0) * sensor.full_well_e
    if sensor.noise:
        electrons = torch.poisson(signal, generator=generator)
        if sensor.read_noise_e > 0:
            electrons = electrons + sensor.read_noise_e * torch.randn(
                signal.shape, generator=generator, dtype=signal.dtype
            )
    else:
        electrons = signal
    if sensor.bit_depth is None:
        return (electrons / sensor.full_well_e).clamp(0.0, 1.0).to(torch.float32).numpy()
    dn = torch.round(sensor.black_level_dn + electrons * sensor.gain_dn_per_e)
    return dn.clamp(0, sensor.white_level).numpy().astype(sensor.dtype)


def normalise(frames: np.ndarray, sensor: SensorModel) -> Tensor:
    """Stored frames back to float32 [0, 1] (black -> 0, white -> 1), as Stack.to_float does."""
    if sensor.bit_depth is None:
        return torch.from_numpy(np.asarray(frames, dtype=np.float32))
    black, white = sensor.black_level_dn, sensor.white_level
    return ((torch.from_numpy(frames.astype(np.float32)) - black) / (white - black)).clamp_(0.0, 1.0)

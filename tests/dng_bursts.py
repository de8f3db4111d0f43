"""Small raw bursts written as DNG files, for tests of the commands that read them (needs the
[raw] extra's pidng; callers skip without it)."""

from pathlib import Path


def write_dng_burst(folder, size: int = 48, frames: int = 4) -> list[str]:
    """``frames`` GRBG mosaics of ``size`` x ``size`` px (chelsea, indoor light, S = 2) as DNG
    files ``f0.dng``, ``f1.dng``, ... in ``folder``; their paths."""
    from hbis_torch.capture.dng import write_mosaic_dng
    from hbis_torch.training.heldout_burst import BurstCondition
    from hbis_torch.training.heldout_raw import BLACK, WHITE, make_raw_burst

    burst = make_raw_burst("chelsea", "GRBG", "indoor", 2, size, 5, BurstCondition("raw", frames=frames))
    return [str(write_mosaic_dng(Path(folder) / f"f{k}.dng", m, "GRBG", BLACK, WHITE))
            for k, m in enumerate(burst.mosaics)]

"""The settings (``$$``) of the rig the GRBL simulator (:mod:`hbis_torch.hardware.sim_machine`)
plays when none are given: GRBL 1.1's defaults with the prism axes' steps, rates and travel."""

from __future__ import annotations

# A plausible prism rig: 1.8 deg motor, 16 microsteps, 4:1 belt -> 200*16*4/360 steps per degree.
PRISM_STEPS_PER_DEG = 200 * 16 * 4 / 360
DEFAULT_SETTINGS: dict[int, float] = {
    0: 10, 1: 25, 2: 0, 3: 0, 4: 0, 5: 0, 6: 0, 10: 1, 11: 0.010, 12: 0.002, 13: 0,
    20: 0, 21: 0, 22: 0, 23: 0, 24: 25.0, 25: 500.0, 26: 250, 27: 1.0, 30: 1000, 31: 0, 32: 0,
    100: PRISM_STEPS_PER_DEG, 101: PRISM_STEPS_PER_DEG, 102: 250.0,
    110: 3600.0, 111: 3600.0, 112: 500.0,
    120: 360.0, 121: 360.0, 122: 10.0,
    130: 360.0, 131: 360.0, 132: 200.0,
}
#: Settings GRBL prints as integers (``$$``); the others with three decimals.
INTEGER_SETTINGS = {0, 1, 2, 3, 4, 5, 6, 10, 13, 20, 21, 22, 23, 26, 30, 31, 32}

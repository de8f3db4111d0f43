"""The training domain of a model: the optics and noise it was trained on, and the check that a
stack lies inside it.

A network is only known to work where it was trained. The random degradations of the training
pool (:mod:`hbis_torch.training.data`) span a range of lens cutoffs (F 1 to
F 8 on the training camera) and of noise levels (full wells of 1,000 to 100,000 e-, read noise of
1 to 15 e-, 8 to 16 bits). A stack blurrier than the blurriest training lens, or far quieter or
noisier than any training sensor, is outside: there the network extrapolates, and on such
stacks it was measured to lose to the classical image it refines (docs/learned.md, "The checks
before the network runs"). The learned method then
returns the classical image and says why (:meth:`LearnedSR.__call__
<hbis_torch.reconstruct.learned.LearnedSR.__call__>`), unless asked to extrapolate.

A model records its domain in its ``metadata_props`` as ``training_domain`` (JSON, written at
export from :func:`hbis_torch.training.data.training_domain`), and the check reads it from
there (:func:`domain_from_metadata`): this run-time side never imports the training pipeline. A
model without it is not checked.

A model is also only as good as its validation says: one that beat the classical image it
refines by less than :data:`MIN_VALIDATION_GAIN_DB` on its own validation set (``val_psnr_db``
against ``val_classical_psnr_db`` in its metadata) has learned nothing the classical method
lacks, and is not used either (:func:`unhelpful_model`).
"""

from __future__ import annotations

import json
import math

# How far past the trained ranges a stack may lie and still count as inside: the noise measured
# on the lattice is good to some 20 % (1.7 times at worst on the held-out photographs), and a
# cutoff 10 % below the blurriest lens is still a lens the training's defocused examples covered.
NOISE_MARGIN = 1.4
CUTOFF_MARGIN = 0.9
# Least gain over the classical image, on the model's own validation set, for the network to be
# used at all (dB).
MIN_VALIDATION_GAIN_DB = 0.1


def noise_at_mid_grey(noise_params: tuple[float, float]) -> float:
    """Standard deviation of the frame noise at half of full scale, sqrt(a / 2 + b): one number
    for the noise whether shot or read noise dominates."""
    a, b = noise_params
    return math.sqrt(max(0.5 * float(a) + float(b), 0.0))


def domain_from_metadata(metadata: dict) -> dict | None:
    """A model's recorded ``training_domain``, or None if it has none (or it does not parse)."""
    text = metadata.get("training_domain")
    if not text:
        return None
    try:
        domain = json.loads(text)
        return {key: [float(v) for v in domain[key]] for key in ("cutoff_cycles_per_px", "noise_at_mid_grey")}
    except (ValueError, KeyError, TypeError):
        return None


def outside_domain(domain: dict | None, noise_params: tuple[float, float], cutoff: float | None) -> str | None:
    """Why a stack lies outside a model's training domain, or None if it lies inside.

    Parameters
    ----------
    domain : dict or None
        :func:`domain_from_metadata` (None: nothing is checked).
    noise_params : (float, float)
        (a, b) of the stack's frame noise, variance ``a x + b``.
    cutoff : float or None
        The stack's lens cutoff, cycles per LR pixel (None: the optics are unknown, not checked).

    Returns
    -------
    str or None
        One sentence naming the quantity, its value and the trained range.
    """
    if domain is None:
        return None
    low_cut = domain["cutoff_cycles_per_px"][0]
    if cutoff is not None and cutoff < CUTOFF_MARGIN * low_cut:
        return (f"the lens cutoff ({cutoff:.2f} cycles per pixel) is below the blurriest lens the "
                f"model was trained on ({low_cut:.2f})")
    noise = noise_at_mid_grey(noise_params)
    lo, hi = domain["noise_at_mid_grey"]
    if not lo / NOISE_MARGIN <= noise <= hi * NOISE_MARGIN:
        return (f"the frames' noise ({100 * noise:.2f} % of full scale at mid-grey) lies outside the "
                f"model's training range ({100 * lo:.2f} to {100 * hi:.2f} %)")
    return None


def validation_gain(metadata: dict) -> float | None:
    """A model's validation PSNR minus that of the classical image it refines on the same
    validation set (dB), from its metadata; None where either is not recorded."""
    try:
        gain = float(metadata["val_psnr_db"]) - float(metadata["val_classical_psnr_db"])
    except (KeyError, ValueError, TypeError):
        return None
    return gain if math.isfinite(gain) else None


def unhelpful_model(metadata: dict) -> str | None:
    """Why a model is not used on any stack (:data:`MIN_VALIDATION_GAIN_DB`), or None."""
    gain = validation_gain(metadata)
    if gain is None or gain >= MIN_VALIDATION_GAIN_DB:
        return None
    return (f"the model beat the classical image by only {gain:+.2f} dB on its validation set (less "
            f"than {MIN_VALIDATION_GAIN_DB} dB)")

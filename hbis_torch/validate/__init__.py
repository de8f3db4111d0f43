"""Observation-space cross-validation: a quality score for super-resolution without ground truth.

Hold a frame out, super-resolve the rest, predict the held-out frame through a forward model
(its sample positions, the pixel's area, a small blur; gain and offset fitted) and score the
prediction by PSNR, beside the single-frame baseline (docs/validate.md).

:mod:`hbis_torch.validate.frames`
    :func:`select_frames` (a stack of some of the frames) and :func:`holdout_frames`.
:mod:`hbis_torch.validate.forward` (from :mod:`hbis_torch.observation.forward`)
    :func:`predict_frame`: the forward model.
:mod:`hbis_torch.validate.score`
    :func:`fit_and_score`: gain and offset, then PSNR away from the border.
:mod:`hbis_torch.validate.baseline`
    :func:`single_frame`: the reference frame enlarged bicubically.
:mod:`hbis_torch.validate.cross`
    :func:`cross_validate`, which runs it all over the methods of the registry.
"""

from hbis_torch.lazy import lazy_exports

# Imported on first use (PEP 562), so that ``hbis validate --help`` comes without torch.
_HOMES = {
    "select_frames": "frames",
    "holdout_frames": "frames",
    "PER_FRAME_KEYS": "frames",
    "predict_frame": "forward",
    "pixel_kernel": "forward",
    "centre_offset": "forward",
    "DEFAULT_BLUR_PX": "forward",
    "fit_and_score": "score",
    "FrameScore": "score",
    "DEFAULT_BORDER_PX": "score",
    "single_frame": "baseline",
    "SINGLE_FRAME": "baseline",
    "cross_validate": "cross",
    "resolve_methods": "cross",
    "Validation": "cross",
    "MethodScores": "cross",
    "DEFAULT_METHODS": "cross",
    "DEFAULT_HOLDOUT": "cross",
}

__all__ = sorted(_HOMES)


__getattr__, __dir__ = lazy_exports(__name__, _HOMES, globals())

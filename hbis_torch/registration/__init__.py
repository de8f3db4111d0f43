"""Sub-pixel registration of a stack of shifted frames against its reference frame.

The Risley scan moves the image by fractions of a pixel between frames. The tracer predicts that
motion (``prediction``); the data then corrects it, because motors miss their targets and the
optics are never exactly the model. The correction is a forward-compositional Lucas-Kanade fit
(Baker & Matthews 2004) of the reference, sampled through each frame's homography, to the frame,
with robust (Huber) weights so that a small occluder does not drag the estimate, and cubic
B-spline resampling (value and exact gradient) so that the warp itself does not bias the
sub-pixel answer (torch's bicubic kernel would, by about 0.04 px). The optics' prediction comes
in as homographies fitted with Kornia's DLT (:func:`homographies_from_positions`).

Frames are (F, H, W); pixel (u, v) is the centre of column u and row v. A homography ``H_k``
maps frame-k pixel coordinates to reference pixel coordinates: ``[u_r, v_r, 1] ~ H_k [u, v, 1]``.

Motion models, simplest first: ``translation`` (2 parameters), ``similarity`` (4: shift, rotation,
scale) and ``homography`` (8). With ``model="auto"`` the simplest model that explains the residual
is kept: a richer model is tried only when a score test on the simpler fit's residual says it
would pay (BIC over the effective number of independent residuals of the blurred frames) and
its extra motion is measurable (it moves some pixel by more than ``motion_tolerance_px``); it is
kept only if the full fit confirms both.

Every frame gets a confidence in [0, 1] and an ``ok`` flag; ``messages`` says why a frame was
flagged: too little texture to register, pixels that do not match (occlusion, a changed scene),
no convergence, or (given a prediction) a frame that sits where another frame of the plan should
be (frames out of order).

The package holds one idea per module: :mod:`.homography` (homographies and the motion models'
parameters), :mod:`.bspline` (prefiltering and cubic B-spline resampling),
:mod:`.phase_correlation` (the coarse start), :mod:`.lucas_kanade` (the fitter),
:mod:`.model_choice`, :mod:`.assess` (confidence and messages) and :mod:`.stack`
(:func:`register_stack` and its :class:`Registration`); a hand-held burst's registration adds
:mod:`.pyramid` (coarse to fine), :mod:`.evidence` (what its per-frame model choice reads),
:mod:`.local` (tile-wise shifts on top of the global motion) and :mod:`.warp` (a frame resampled
onto the reference grid). The per-frame statistics (mean, spread, noise level) are
:mod:`hbis_torch.sensor.noise`'s.
"""

from hbis_torch.registration.assess import (
    MIN_CORRELATION,
    OCCLUSION_FRACTION,
    PRECISION_SCALE_PX,
)
from hbis_torch.registration.bspline import bspline_sample, gaussian_kernel, prefilter
from hbis_torch.registration.homography import (
    ALL_MODELS,
    MODELS,
    N_PARAMS,
    apply_homography,
    apply_homography_to_grid,
    fit_grid,
    homographies_from_grid,
    homographies_from_positions,
    lk_motion_difference,
)
from hbis_torch.registration.lucas_kanade import COARSE_POINTS
from hbis_torch.registration.phase_correlation import phase_correlation_shifts
from hbis_torch.registration.stack import Registration, register_models, register_stack
from hbis_torch.sensor.noise import noise_sigma

__all__ = [
    "ALL_MODELS",
    "COARSE_POINTS",
    "MIN_CORRELATION",
    "MODELS",
    "N_PARAMS",
    "OCCLUSION_FRACTION",
    "PRECISION_SCALE_PX",
    "Registration",
    "apply_homography",
    "apply_homography_to_grid",
    "bspline_sample",
    "fit_grid",
    "gaussian_kernel",
    "homographies_from_grid",
    "homographies_from_positions",
    "lk_motion_difference",
    "noise_sigma",
    "phase_correlation_shifts",
    "prefilter",
    "register_models",
    "register_stack",
]

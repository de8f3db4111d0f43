"""The forward model cross-validation predicts frames through: it lives in
:mod:`hbis_torch.observation.forward`, below both validation and the learned method's burst
adaptation, which share it; this module keeps the old import path."""

from hbis_torch.observation.forward import DEFAULT_BLUR_PX, centre_offset, pixel_kernel, predict_frame

__all__ = ["DEFAULT_BLUR_PX", "centre_offset", "pixel_kernel", "predict_frame"]

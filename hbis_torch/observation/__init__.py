"""The forward model of an observation: what a frame should record, given an image on the output
grid and where the frame's samples lie on it.

It sits below both of its users, so that neither imports the other for it:

* :mod:`hbis_torch.validate` predicts held-out frames through it to score a reconstruction;
* :mod:`hbis_torch.reconstruct.learned.adapt` fine-tunes the network on a burst's own frames
  through the same prediction.

:mod:`hbis_torch.observation.forward`
    :func:`~hbis_torch.observation.forward.predict_frame`,
    :func:`~hbis_torch.observation.forward.pixel_kernel` (centred by
    :func:`~hbis_torch.observation.forward.centre_offset`, read by
    :func:`~hbis_torch.observation.forward.sample_grid`) and
    :data:`~hbis_torch.observation.forward.DEFAULT_BLUR_PX`.

Nothing is imported here, so that importing the package costs nothing (torch comes with
:mod:`~hbis_torch.observation.forward`).
"""

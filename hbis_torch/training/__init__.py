"""The learned method's build side: what makes a model, never what runs one.

The network in torch (:mod:`.net`: :class:`~hbis_torch.reconstruct.learned.network.HbisSRNet`,
built from an :class:`~hbis_torch.reconstruct.learned.architecture.Architecture` by
:func:`~hbis_torch.reconstruct.learned.network.build_net`, and what training adds), the
training-data pipeline and its training domain (:mod:`.data`), the ONNX export and its parity
check (:mod:`.export`, :mod:`.onnx_rewrite`), and what the scripts in ``training/`` and
``benchmarks/`` share: the held-out matrix (:mod:`.heldout`, with its second forward model
:mod:`.independent_render`) and the network variants of the A/B (:mod:`.variants`).

This package sits above :mod:`hbis_torch.reconstruct`: it imports the run-time side (the inputs,
the runtime, the architecture record, the network), and nothing there imports it, so running a
model needs no training pipeline (and onnxruntime's path not torch's network either). Nothing is
imported here: import the modules.
"""

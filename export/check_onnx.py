"""Check an exported SR model: torch and onnxruntime agree at a size other than the export size.

    python export/check_onnx.py models/hbis_sr_h4.onnx runs/sr_h4/model.pt [--size 45 67]

Prints the largest absolute difference of the two outputs for each execution provider this
onnxruntime has (its own CPU kernels, and OpenVINO where installed); exits 1 if one exceeds 1e-4.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout: repo first
from export.export_onnx import EXPORT_SIZE, example_inputs, load_checkpoint  # noqa: E402
from hbis_torch.reconstruct.learned import LearnedSR, available_providers  # noqa: E402

TOLERANCE = 1e-4
CHECK_SIZE = (45, 67)  # deliberately not EXPORT_SIZE, and odd


def check_parity(onnx_path, checkpoint, size=CHECK_SIZE, seed: int = 1, provider: str = "auto") -> float:
    """Max |torch - onnxruntime| of the raw network outputs on random inputs of ``size``.

    ``checkpoint`` is a model.pt path or the HbisSRNet itself; ``provider`` the onnxruntime
    execution provider (:func:`hbis_torch.reconstruct.learned.execution_providers`).
    """
    if tuple(size) == tuple(EXPORT_SIZE):
        raise ValueError("check at a size other than the export size")
    model = checkpoint if isinstance(checkpoint, torch.nn.Module) else load_checkpoint(checkpoint)[0]
    model = model.eval()
    frames, offsets = example_inputs(model.h, *size, seed=seed)
    with torch.no_grad():
        expected = model(frames, offsets).numpy()
    runner = LearnedSR(onnx_path, provider=provider)
    got = runner.session.run(["image"], {"frames": frames.numpy(), "offsets": offsets.numpy()})[0]
    if got.shape != expected.shape:
        raise AssertionError(f"onnxruntime output {got.shape} != torch output {expected.shape}")
    return float(np.abs(got - expected).max())


def check_parity_all(onnx_path, checkpoint, size=CHECK_SIZE) -> dict[str, float]:
    """:func:`check_parity` for every execution provider this onnxruntime has, by name."""
    return {provider: check_parity(onnx_path, checkpoint, size, provider=provider)
            for provider in available_providers()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("onnx")
    parser.add_argument("checkpoint")
    parser.add_argument("--size", type=int, nargs=2, default=CHECK_SIZE, metavar=("H", "W"))
    args = parser.parse_args(argv)
    diffs = check_parity_all(args.onnx, args.checkpoint, args.size)
    for provider, diff in diffs.items():
        print(f"max abs diff torch vs onnxruntime ({provider}) at {args.size[0]} x {args.size[1]}: "
              f"{diff:.2e} (tolerance {TOLERANCE:.0e})")
    return 0 if max(diffs.values()) <= TOLERANCE else 1


if __name__ == "__main__":
    raise SystemExit(main())

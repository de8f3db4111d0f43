"""Check an exported SR model: torch and onnxruntime agree at a size other than the export size.

    python export/check_onnx.py hbis_torch/models/hbis_sr_h4.onnx runs/sr_h4/model.pt [--size 45 67]

Prints the largest absolute difference of the two outputs for each execution provider this
onnxruntime has (its own CPU kernels, and OpenVINO where installed); exits 1 if one exceeds 1e-4.
"""

from __future__ import annotations

import argparse

from hbis_torch.training.export import CHECK_SIZE, TOLERANCE, check_parity_all


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

"""Write the int8 file of SR models: static QDQ quantisation, per-channel weights, calibrated on the training pool.

    python export/quantize_int8.py hbis_torch/models/hbis_sr_h4.onnx [MORE.onnx ...] [--overwrite]
        [--count 48] [--seed 31000] [--method percentile]

Each MODEL.onnx (any file of the hbis-sr-onnx/2 format: the shipped models or one a training run
exported) gets MODEL.int8.onnx beside it (:mod:`hbis_torch.training.quantize` says how and why),
which ``hbis reconstruct --method learned --precision int8`` runs. An existing int8 file is
refused unless --overwrite. export/check_int8.py compares the two on the held-out matrix.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hbis_torch.errors import HbisInputError
from hbis_torch.training.quantize import CALIBRATION_COUNT, CALIBRATION_METHOD, CALIBRATION_SEED, quantize_model


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("models", type=Path, nargs="+", metavar="MODEL.onnx", help="float32 model files")
    parser.add_argument("--count", type=int, default=CALIBRATION_COUNT, help="training-pool examples to calibrate on")
    parser.add_argument("--seed", type=int, default=CALIBRATION_SEED, help="the calibration pool's seed")
    parser.add_argument("--method", choices=("minmax", "percentile", "entropy"), default=CALIBRATION_METHOD,
                        help="how the activations' ranges are calibrated")
    parser.add_argument("--overwrite", action="store_true", help="replace existing int8 files")
    args = parser.parse_args(argv)
    try:
        for model in args.models:
            out = quantize_model(model, count=args.count, seed=args.seed, method=args.method,
                                 overwrite=args.overwrite)
            print(f"wrote {out} ({out.stat().st_size / 1e3:.0f} kB, from {model.stat().st_size / 1e3:.0f} kB)")
    except HbisInputError as exc:
        print(f"quantize_int8: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

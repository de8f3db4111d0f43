"""Export a trained SR checkpoint to ONNX (opset 18, dynamic batch, height and width).

    python export/export_onnx.py runs/sr_h4/model.pt hbis_torch/models/hbis_sr_h4.onnx
    python export/export_onnx.py hbis_torch/models/hbis_sr_h4.pt hbis_torch/models/hbis_sr_h4.onnx   # re-export shipped weights

The file is self-contained (weights inside, no .data file) and its ``metadata_props`` carry
what a user of the model needs: ``format``, ``h``, ``frames`` (= h^2), ``normalisation``,
``training_commit`` (git HEAD when the checkpoint was trained), ``export_commit``, ``opset``,
``parameters``, ``val_psnr_db``, ``training_config`` (JSON) and ``graph_rewrites`` (what
hbis_torch/training/onnx_rewrite.py changed in the exporter's graph). After writing,
the parity of torch and onnxruntime is checked at a size other than the export size
(export/check_onnx.py). The work is done by hbis_torch.training.export; this is its
command line.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from hbis_torch.io_utils import atomic_path
from hbis_torch.training.export import OPSET, TOLERANCE, check_parity_all, export, load_checkpoint


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", help="model.pt written by training/train_sr.py, or a weights file "
                        "written by --weights (hbis_torch/models/hbis_sr_h*.pt)")
    parser.add_argument("out", help="the .onnx file to write")
    parser.add_argument("--opset", type=int, default=OPSET)
    parser.add_argument("--weights", help="also write the float32 weights (no optimizer state) to this .pt, "
                        "for eager-torch comparisons and fine-tuning")
    parser.add_argument("--no-check", action="store_true", help="skip the torch/onnxruntime parity check")
    args = parser.parse_args(argv)
    metadata = export(args.checkpoint, args.out, args.opset)
    size = Path(args.out).stat().st_size
    print(f"wrote {args.out} ({size / 1e6:.2f} MB, opset {args.opset}, h = {metadata['h']})")
    if args.weights:
        model, ckpt = load_checkpoint(args.checkpoint)
        slim = {"model": model.state_dict(), "model_config": model.config(), "metadata": metadata}
        with atomic_path(args.weights) as tmp:
            torch.save(slim, tmp)
            tmp.chmod(0o644)
        print(f"wrote {args.weights} ({Path(args.weights).stat().st_size / 1e6:.2f} MB)")
    if args.no_check:
        return 0
    diffs = check_parity_all(args.out, args.checkpoint)
    for provider, diff in diffs.items():
        print(f"parity torch vs onnxruntime ({provider}): max abs diff {diff:.2e} (tolerance {TOLERANCE:.0e})")
    return 0 if max(diffs.values()) <= TOLERANCE else 1


if __name__ == "__main__":
    from hbis_torch.errors import HbisInputError

    try:
        raise SystemExit(main())
    except HbisInputError as exc:  # a checkpoint that needs pickle, a missing file: one line, exit 2
        print(f"export_onnx: error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None

"""Export a trained SR checkpoint to ONNX (opset 18, dynamic batch, height and width).

    python export/export_onnx.py runs/sr_h4/model.pt models/hbis_sr_h4.onnx
    python export/export_onnx.py models/hbis_sr_h4.pt models/hbis_sr_h4.onnx   # re-export shipped weights

The file is self-contained (weights inside, no .data file) and its ``metadata_props`` carry
what a user of the model needs: ``format``, ``h``, ``frames`` (= h^2), ``normalisation``,
``training_commit`` (git HEAD when the checkpoint was trained), ``export_commit``, ``opset``,
``parameters``, ``val_psnr_db``, ``training_config`` (JSON) and ``graph_rewrites`` (what
export/onnx_rewrite.py changed in the exporter's graph). After writing, the parity of
torch and onnxruntime is checked at a size other than the export size (export/check_onnx.py).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout: repo first
from export.onnx_rewrite import fuse_depth_to_space  # noqa: E402
from hbis_torch.io_utils import atomic_path  # noqa: E402
from hbis_torch.reconstruct.learned import MODEL_FORMAT, NORMALISATION  # noqa: E402
from hbis_torch.reconstruct.net import HbisSRNet, count_parameters  # noqa: E402

OPSET = 18
EXPORT_SIZE = (32, 40)  # (H, W) of the example inputs traced at export; any size runs after


def git_head() -> str:
    """``git rev-parse HEAD`` of the repository holding this file, or "unknown"."""
    try:
        return subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=Path(__file__).resolve().parent,
            capture_output=True, text=True, check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def load_checkpoint(path) -> tuple[HbisSRNet, dict]:
    """The model (eval mode, float32) and the raw checkpoint dict."""
    ckpt = torch.load(path, map_location="cpu", weights_only=False)
    model = HbisSRNet(**ckpt["model_config"])
    model.load_state_dict(ckpt["model"])
    return model.eval(), ckpt


def example_inputs(h: int, rows: int, cols: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Random frames (1, h^2, rows, cols) in [0, 1] and offsets (1, 2h^2, rows, cols) in +-0.5."""
    g = torch.Generator().manual_seed(seed)
    frames = torch.rand(1, h * h, rows, cols, generator=g)
    offsets = torch.rand(1, 2 * h * h, rows, cols, generator=g) - 0.5
    return frames, offsets


def export_model(model: HbisSRNet, out_path, info: dict | None = None, opset: int = OPSET,
                 rewrite: bool = True) -> dict:
    """Export ``model`` to ``out_path`` (written atomically); returns the metadata written.

    ``info`` is the training checkpoint (or any dict) with ``git_commit``, ``val_psnr``,
    ``step`` and ``config``; missing entries are recorded as unknown. ``rewrite``: replace the
    exporter's reshape/transpose depth-to-space with ONNX DepthToSpace
    (:func:`export.onnx_rewrite.fuse_depth_to_space`; same outputs, faster in onnxruntime).
    """
    import onnx

    info = info or {}
    model = model.eval()
    frames, offsets = example_inputs(model.h, *EXPORT_SIZE)
    batch, rows, cols = (torch.export.Dim(n, min=1, max=8192) for n in ("batch", "height", "width"))
    dims = {0: batch, 2: rows, 3: cols}
    program = torch.onnx.export(
        model, (frames, offsets), input_names=["frames", "offsets"], output_names=["image"],
        dynamic_shapes={"frames": dims, "offsets": dims}, opset_version=opset, dynamo=True,
        external_data=False, verbose=False,
    )
    proto = program.model_proto
    fused = fuse_depth_to_space(proto, model.h) if rewrite else 0
    metadata = {
        "format": MODEL_FORMAT,
        "h": str(model.h),
        "frames": str(model.frame_count),
        "normalisation": NORMALISATION,
        "training_commit": str(info.get("git_commit", "unknown")),
        "export_commit": git_head(),
        "opset": str(opset),
        "parameters": str(count_parameters(model)),
        "model_config": json.dumps(model.config()),
        "val_psnr_db": f"{float(info.get('val_psnr', float('nan'))):.3f}",
        "training_steps": str(info.get("step", "unknown")),
        "training_config": json.dumps(info.get("config", {})),
        "graph_rewrites": f"DepthToSpace x{fused}",
    }
    del proto.metadata_props[:]
    for key, value in metadata.items():
        proto.metadata_props.add(key=key, value=value)
    proto.doc_string = f"hbis-torch multi-frame SR network, h = {model.h}; see models/README.md"
    onnx.checker.check_model(proto)
    with atomic_path(out_path) as tmp:
        onnx.save(proto, str(tmp))
        tmp.chmod(0o644)
    return metadata


def training_info(ckpt: dict) -> dict:
    """What :func:`export_model` records about training, from a training checkpoint or from a
    weights file written by ``--weights`` (models/hbis_sr_h*.pt), whose ``metadata`` is that of
    the first export: a re-export keeps the training commit, validation PSNR, steps and config."""
    if "metadata" not in ckpt:
        return ckpt
    meta = ckpt["metadata"]
    return {"git_commit": meta.get("training_commit", "unknown"),
            "val_psnr": float(meta.get("val_psnr_db", "nan")),
            "step": meta.get("training_steps", "unknown"),
            "config": json.loads(meta.get("training_config", "{}"))}


def export(checkpoint, out_path, opset: int = OPSET) -> dict:
    """Export a checkpoint written by training/train_sr.py, or a weights file written by
    ``--weights``; returns the metadata written."""
    model, ckpt = load_checkpoint(checkpoint)
    return export_model(model, out_path, training_info(ckpt), opset)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", help="model.pt written by training/train_sr.py, or a weights file "
                        "written by --weights (models/hbis_sr_h*.pt)")
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
    from export.check_onnx import TOLERANCE, check_parity_all

    diffs = check_parity_all(args.out, args.checkpoint)
    for provider, diff in diffs.items():
        print(f"parity torch vs onnxruntime ({provider}): max abs diff {diff:.2e} (tolerance {TOLERANCE:.0e})")
    return 0 if max(diffs.values()) <= TOLERANCE else 1


if __name__ == "__main__":
    raise SystemExit(main())

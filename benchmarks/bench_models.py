"""What the shipped SR models record about themselves, in one results file.

    python benchmarks/bench_models.py [--out benchmarks/results/bench_models.json]

Reads each shipped model's ONNX metadata (no network runs): h, tier, parameters, multiply-adds
per LR pixel, training steps of the kept checkpoint, training pool version, the validation PSNR
of the network and of the classical image it refines, and the commits that trained and exported
it. docs/learned.md quotes these; ``hbis_torch/models/README.md`` says how each was trained.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from hbis_torch.provenance import write_results

REPO = Path(__file__).resolve().parents[1]


def describe(path: Path) -> dict:
    """One model's record, from its metadata."""
    from hbis_torch.reconstruct.learned import read_model_metadata
    from hbis_torch.reconstruct.learned.architecture import Architecture
    from hbis_torch.training.net import build_net
    from hbis_torch.training.variants import macs_per_pixel

    meta = read_model_metadata(path)
    training = json.loads(meta.get("training_config", "{}"))
    return {"file": path.name, "h": int(meta["h"]), "tier": "best" if path.stem.endswith("_best") else "fast",
            "parameters": int(meta["parameters"]),
            "macs_per_lr_pixel": macs_per_pixel(build_net(Architecture.from_metadata(meta))),
            "training_steps": int(meta["training_steps"]), "pool_version": training.get("POOL_VERSION"),
            "val_psnr_db": float(meta["val_psnr_db"]), "val_classical_psnr_db": float(meta["val_classical_psnr_db"]),
            "training_commit": meta.get("training_commit"), "export_commit": meta.get("export_commit")}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "bench_models.json")
    args = parser.parse_args(argv)
    from hbis_torch.reconstruct.learned import models_dir

    files = sorted(p for p in models_dir().glob("hbis_sr_h*.onnx") if not p.name.endswith(".int8.onnx"))
    write_results(args.out, {"models": [describe(p) for p in files]}, argv=argv)
    print(f"wrote {args.out} ({len(files)} models)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

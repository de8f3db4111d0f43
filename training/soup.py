"""Mix the weights of two runs of one network (a "model soup", Wortsman et al., ICML 2022) and
score each mix on train_sr.py's validation set.

    python training/soup.py A.pt B.pt --alphas 0 0.25 0.5 0.75 1 --out-dir training/runs/soup_h7

Each mix is ``(1 - alpha) A + alpha B``, parameter by parameter: it works where B was trained on
from A (or both from one start), so that the straight line between them stays in one basin.
Each is written as ``soup_a{alpha}.pt``, a checkpoint that ``export/export_onnx.py`` takes, with
its own validation PSNR (the figure the learned method's gain check reads) and B's training
record plus ``soup`` (A, B, alpha). ``training/eval_matrix.py --photos`` with training
photographs then compares the mixes without touching the held-out ones.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from hbis_torch.io_utils import atomic_path
from hbis_torch.metrics import psnr
from hbis_torch.training.data import build_pool, whole_example
from hbis_torch.training.export import load_checkpoint, training_info
from hbis_torch.training.net import depth_to_space


def mix(a: dict, b: dict, alpha: float) -> dict:
    """``(1 - alpha) a + alpha b`` of two state dicts of one architecture (same keys and shapes)."""
    return {k: torch.lerp(a[k].double(), b[k].double(), alpha).to(a[k].dtype) for k in a}


@torch.no_grad()
def validation_psnr(model, val_set, h: int) -> tuple[float, float]:
    """Mean PSNR (dB) of the network and of the classical image it refines, as train_sr.py's validate()."""
    net, classical = [], []
    for base, noise, truth in val_set:
        base, noise, truth = (torch.from_numpy(x) for x in (base, noise, truth))
        net.append(psnr(model(base, noise).clamp(0, 1), truth))
        classical.append(psnr(depth_to_space(base, h), truth))
    return sum(net) / len(net), sum(classical) / len(classical)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("a", type=Path, help="weights at alpha = 0 (a model.pt, or a shipped .pt)")
    parser.add_argument("b", type=Path, help="weights at alpha = 1; its training record is kept")
    parser.add_argument("--alphas", type=float, nargs="+", default=[0.0, 0.25, 0.5, 0.75, 1.0])
    parser.add_argument("--out-dir", type=Path, required=True)
    args = parser.parse_args(argv)
    if any(not 0.0 <= x <= 1.0 for x in args.alphas):
        parser.error("every alpha must lie in [0, 1]")
    model_a, _ = load_checkpoint(args.a)
    model_b, ckpt_b = load_checkpoint(args.b)
    if model_a.config() != model_b.config():
        raise SystemExit(f"soup: {args.a} and {args.b} are different architectures")
    info = training_info(ckpt_b)
    config = info.get("config", {})
    h = int(model_b.config()["h"])
    # train_sr.py's validation stacks: their seed is the run's + 1
    pool = build_pool(h, int(config.get("val_size", 16)), int(config.get("val_roi", 64)), int(config.get("seed", 0)) + 1)
    val_set = [whole_example(ex, h) for ex in pool]
    args.out_dir.mkdir(parents=True, exist_ok=True)
    # copies: model_b.state_dict() holds the live tensors that each mix is loaded into
    state_a, state_b = ({k: v.clone() for k, v in m.state_dict().items()} for m in (model_a, model_b))
    for alpha in args.alphas:
        model_b.load_state_dict(mix(state_a, state_b, alpha))
        val, classical = validation_psnr(model_b, val_set, h)
        out = args.out_dir / f"soup_a{alpha:g}.pt"
        ckpt = {**info, "model": model_b.state_dict(), "model_config": model_b.config(), "val_psnr": val,
                "val_classical_psnr": classical,
                "config": {**config, "soup": json.dumps({"a": str(args.a), "b": str(args.b), "alpha": alpha})}}
        with atomic_path(out) as tmp:
            torch.save(ckpt, tmp)
        print(f"alpha {alpha:g}: validation PSNR {val:.3f} dB (classical {classical:.3f} dB) -> {out}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

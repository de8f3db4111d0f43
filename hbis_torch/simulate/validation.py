"""A fixed validation set on disk: items of a SyntheticStacks dataset as stack and truth files.

Layout of the output folder::

    config.json             the DatasetConfig (as JSON) the set was drawn from
    val_00000.tif           item 0 as an hbis-stack/1 stack (integer frames, planned phases)
    val_00000_truth.tif     its ground truth, float32 (h*H, h*W), JSON description with h, roi
    ...
    index.json              {"config": ..., "items": [{"index", "stack", "truth", "h", "roi", ...}]}

Writing resumes: items whose two files exist are kept, so an interrupted run picks up where it
stopped; a folder drawn from another configuration is refused. Run as a script::

    python3 -m hbis_torch.simulate.validation --out data/val --count 256 --seed 1000
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from hbis_torch.errors import HbisInputError
from hbis_torch.io_utils import atomic_write_text
from hbis_torch.stack_io import write_image, write_stack
from hbis_torch.simulate.dataset import DatasetConfig, SyntheticStacks


def config_to_dict(config: DatasetConfig) -> dict:
    """The configuration as plain JSON data (tuples become lists)."""
    return json.loads(json.dumps(dataclasses.asdict(config)))


def write_validation_set(out_dir, config: DatasetConfig, progress: bool = True) -> dict:
    """Write every item of ``SyntheticStacks(config)`` to ``out_dir`` (resuming); return the index.

    Parameters
    ----------
    out_dir : path
        Output folder (created).
    config : DatasetConfig
        ``config.length`` items are written; use a seed not used for training.
    progress : bool
        Show a tqdm progress bar.
    """
    from tqdm import tqdm

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    wanted = config_to_dict(config)
    config_path = out / "config.json"
    if config_path.exists():
        try:
            found = json.loads(config_path.read_text())
        except json.JSONDecodeError:
            raise HbisInputError(f"{config_path}: not JSON; remove the folder or choose another") from None
        if found != wanted:
            raise HbisInputError(
                f"{out} holds a validation set of a different configuration; choose another folder"
            )
    else:
        atomic_write_text(config_path, json.dumps(wanted, indent=1))
    dataset = SyntheticStacks(config)
    items = []
    for i in tqdm(range(len(dataset)), desc="validation set", unit="stack", disable=not progress):
        stack_name, truth_name = f"val_{i:05d}.tif", f"val_{i:05d}_truth.tif"
        if (out / stack_name).exists() and (out / truth_name).exists():
            draw = dataset.draw(i)
        else:
            stack, truth, draw = dataset.stack(i)
            write_stack(out / stack_name, stack)
            write_image(out / truth_name, truth, {"format": "hbis-truth/1", "h": draw.h, "roi": list(draw.roi),
                                                  "reference_index": stack.reference_index, "stack": stack_name})
        items.append({"index": i, "stack": stack_name, "truth": truth_name, **draw.to_dict()})
    index = {"config": wanted, "items": items}
    index = json.loads(json.dumps(index))
    atomic_write_text(out / "index.json", json.dumps(index, indent=1))
    return index


def _ints(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(t) for t in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python3 -m hbis_torch.simulate.validation",
        description="Write a fixed validation set of synthetic stacks (stack + truth TIFFs and an "
        "index.json); rerunning resumes. Other DatasetConfig values keep their defaults.",
    )
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--count", type=int, default=256, help="number of stacks (default 256)")
    parser.add_argument("--seed", type=int, default=1000, help="dataset seed (default 1000; keep it "
                        "apart from the training seed)")
    parser.add_argument("--crop", type=_ints, default=(64, 64), help="frame width,height (default 64,64)")
    parser.add_argument("--h", type=_ints, default=(4,), help="h values to draw from, e.g. 2,3,4 (default 4)")
    args = parser.parse_args(argv)
    try:
        if len(args.crop) != 2:
            raise HbisInputError("--crop takes width,height")
        config = DatasetConfig(length=args.count, crop=args.crop, h_choices=args.h, seed=args.seed)
        index = write_validation_set(args.out, config)
    except HbisInputError as exc:
        print(f"validation: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {len(index['items'])} stacks to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

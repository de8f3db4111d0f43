"""Train the SR network (hbis_torch.training.net), the refiner of the classical image, on simulated scans.

Read it top to bottom: config, setup, data, the loop. One process:

    python training/train_sr.py h=4 max_minutes=20 out_dir=training/runs/sr_h4

Two processes on one machine (DDP over gloo on the CPU, over NCCL on GPUs, the same script unchanged):

    torchrun --standalone --nproc_per_node=2 training/train_sr.py h=4 max_minutes=20

On a GPU (``device=auto``, the default, takes one where torch sees one), with bf16 autocast and a
larger network grown from a shipped one (:func:`hbis_torch.training.net.grow_net`):

    python training/train_sr.py --device cuda h=4 width=64 blocks=8 batch_size=32 bf16=True \
        init_from=hbis_torch/models/hbis_sr_h4.pt pool_workers=8 prefetch=4

Quantisation-aware fine-tuning of a trained network for its int8 file (hbis_torch.training.qat;
``quantize_int8.py`` then takes the ranges it trained with from the exported file):

    python training/train_sr.py h=4 qat=True init_from=hbis_torch/models/hbis_sr_h4.pt lr=3e-4 max_minutes=6.5

(``qat_teacher=True``: the target is the float network's output, not the truth.)

Any name in the config block can be overridden as ``name=value`` or ``--name value`` (Python
literals). Killing the run and starting the same command again resumes from ``out_dir/ckpt.pt``,
on any device: a long run can be split into sittings (``max_minutes`` counts the training time
of all of them). The outputs in
``out_dir``: ``ckpt.pt`` (latest, for resuming), ``model.pt`` (best validation PSNR),
``history.json`` and ``val_psnr.png`` (the validation curve against the classical image it refines).
The training stacks draw their optics, noise, scan and reference frame at random
(hbis_torch.training.data); the held-out test on photographs and forward
models the training never used is training/eval_matrix.py.
"""

from __future__ import annotations

import ast
import json
import math
import multiprocessing
import os
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
import torch.nn.functional as F

from hbis_torch.io_utils import atomic_path, atomic_write_text
from hbis_torch.metrics import psnr
from hbis_torch.run_lock import exit_with_parent, lock_dir, remove_temp_files
from hbis_torch.reconstruct.learned.architecture import Architecture
from hbis_torch.training.burst_data import BURST_POOL_VERSION, build_burst_pool, training_domain_with_bursts
from hbis_torch.training.data import (POOL_VERSION, build_pool, load_pool, make_batch, save_pool, training_domain,
                                      whole_example)
from hbis_torch.training.net import build_net, count_parameters, depth_to_space, grow_net
from hbis_torch.training.qat import QuantSim, observe_ranges
from hbis_torch.training.quantize import calibration_inputs

# ---------------------------------------------------------------------------- config
h = 4  # resolution improvement factor; the model takes h*h frames
width = 32  # feature channels
blocks = 4  # residual blocks
kind = "plain"  # the residual blocks: "plain" (the shipped design) or "ir" (inverted residuals)
patch = 32  # LR patch side of a training example (the output patch is h times larger)
pool_size = 480  # simulated training stacks (random scenes, optics, noise and scans, see hbis_torch.training.data)
pool_roi = 96  # LR side of each simulated training stack; patches are cropped from them
val_size = 24  # validation stacks (their own seeds, never trained on; same random degradations)
val_roi = 64  # LR side of a validation stack (PSNR over the whole h*val_roi square)
burst_pool_size = 0  # simulated bursts (freely moving camera, hbis_torch.training.burst_data) added to the pool
burst_roi = 48  # LR side of a burst's frames
burst_val_size = 0  # validation bursts, added to the validation set
cache_dir = "training/runs/cache"  # simulated pools are generated once and reused
batch_size = 8  # per process
lr = 3e-4  # peak learning rate (AdamW), cosine decay to lr/20 over the budget: the network learns a small
# correction of an image already near 45 dB, and at 2e-3 its first steps throw it far off
weight_decay = 1e-4
grad_clip = 1.0  # largest gradient norm (0: no clipping); guards against loss spikes at the peak lr
warmup_steps = 200
loss_kind = "db"  # "db": each crop's PSNR gain over its classical image (see crop_loss); "l1"
loss_floor = 1e-9  # "db" loss: MSE added to both of its sides, so that crops cleaner than this (1e-5: 50 dB) count less
max_steps = 100_000  # whichever of max_steps / max_minutes comes first ends the run
max_minutes = 20.0  # wall-clock budget for training (validation included)
eval_interval = 100  # steps between validation + checkpoint
seed = 0
threads = 0  # torch threads per process; 0: the CPUs divided among the processes
out_dir = "training/runs/sr_h4"
resume = True
progress_bar = True
device = "auto"  # "auto" (a GPU where torch sees one, else the CPU), "cpu" or "cuda"
bf16 = False  # bf16 autocast of the forward pass on a GPU (the loss and the weights stay float32)
init_from = ""  # weights (a .pt of export_onnx.py --weights, or a model.pt) of a smaller plain network to grow from
qat = False  # quantisation-aware fine-tuning of init_from's network (same architecture) for its int8 file
# (hbis_torch.training.qat): trained and validated as onnxruntime's int8 file computes it
qat_calibration_count = 48  # calibration-pool examples its ranges are measured on (as the int8 file's calibration)
qat_teacher = False  # with qat: the loss's target is init_from's float network's output, not the truth (distillation:
# the int8 file learns to compute what the float file does)
pool_workers = 1  # processes that simulate a pool not yet cached (each example has its own seed: same pool)
pool_scheduler = ""  # or a running Dask scheduler's ADDRESS that simulates it, one task per example: the same pool
# (docs/scale-out.md; not local:N, whose spawned workers would run this script again: pool_workers is that)
prefetch = 0  # batches prepared ahead in threads (0: each batch when it is needed); the same batches either way

# ---------------------------------------------------------------------------- overrides
config_keys = [k for k, v in dict(globals()).items() if not k.startswith("_") and isinstance(v, (int, float, str, bool))]


def _as_overrides(argv: list[str]) -> list[str]:
    """``--name value`` and ``--name=value`` as ``name=value``; other arguments unchanged."""
    out, i = [], 0
    while i < len(argv):
        arg = argv[i]
        if arg.startswith("--") and "=" not in arg and i + 1 < len(argv):
            out.append(f"{arg[2:]}={argv[i + 1]}")
            i += 2
            continue
        out.append(arg[2:] if arg.startswith("--") else arg)
        i += 1
    return out


for arg in _as_overrides(sys.argv[1:]):
    key, _, value = arg.partition("=")
    if key not in config_keys or not _:
        raise SystemExit(f"unknown or malformed override {arg!r}; known: {', '.join(config_keys)}")
    try:
        parsed = ast.literal_eval(value)
    except (ValueError, SyntaxError):
        parsed = value  # a bare string such as out_dir=runs/x
    if type(parsed) is not type(globals()[key]) and not (isinstance(globals()[key], float) and isinstance(parsed, int)):
        raise SystemExit(f"{key} must be {type(globals()[key]).__name__}, got {value!r}")
    globals()[key] = type(globals()[key])(parsed)
if pool_scheduler.startswith("local"):  # before any work
    raise SystemExit("pool_scheduler takes a running scheduler's address; on this machine use pool_workers=N")
config = {k: globals()[k] for k in config_keys}
architecture = Architecture(h, width=width, blocks=blocks, kind=kind)  # the net; checkpoints, export, runtime read it

# ---------------------------------------------------------------------------- setup
def git_commit() -> str:
    """HEAD of this checkout (with "-dirty" if files differ from it), stored in checkpoints."""
    here = Path(__file__).resolve().parent
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here, capture_output=True, text=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("-dirty" if dirty else "")


if device not in ("auto", "cpu", "cuda"):
    raise SystemExit(f"train_sr: device must be auto, cpu or cuda, got {device!r}")
use_cuda = device == "cuda" or (device == "auto" and torch.cuda.is_available())
if use_cuda and not torch.cuda.is_available():
    raise SystemExit("train_sr: device=cuda, but torch sees no GPU (device=cpu or auto trains on the CPU)")
ddp = "RANK" in os.environ
if ddp:
    exit_with_parent()  # a worker ends with its launcher (torchrun killed outright)
    dist.init_process_group("nccl" if use_cuda else "gloo")
    rank, world = dist.get_rank(), dist.get_world_size()
else:
    rank, world = 0, 1
master = rank == 0
dev = torch.device("cuda", int(os.environ.get("LOCAL_RANK", 0)) % torch.cuda.device_count()) if use_cuda \
    else torch.device("cpu")
if use_cuda:
    torch.cuda.set_device(dev)
torch.set_num_threads(threads or max(1, len(os.sched_getaffinity(0)) // world))
torch.manual_seed(seed)  # same initial weights on every rank (DDP also broadcasts them)
out = Path(out_dir)
commit = git_commit()
# the optics and noise this pool spans: the model's domain
domain = training_domain_with_bursts() if burst_pool_size > 0 else training_domain()
if master:
    try:
        out_lock = lock_dir(out)  # one run per out_dir; released when this process ends
    except ValueError as exc:
        raise SystemExit(f"train_sr: {exc}") from None
    for tmp in remove_temp_files(out):
        print(f"removed {tmp.name}, left by a run that was killed")

def initial_model():
    """The network of ``architecture``: fresh from ``seed``, or grown from ``init_from``'s weights."""
    if not init_from:
        return build_net(architecture)
    small = torch.load(init_from, map_location="cpu", weights_only=False)
    source = build_net(small["model_config"])
    source.load_state_dict(small["model"])
    return grow_net(source, architecture)


if qat and not init_from:
    raise SystemExit("train_sr: qat=True fine-tunes a trained network: give it init_from")
if qat_teacher and not qat:
    raise SystemExit("train_sr: qat_teacher=True is for qat=True")
if qat and bf16:  # the int8 rounding is emulated in float32; bf16 would round the features again
    raise SystemExit("train_sr: qat=True trains in float32; drop bf16=True")
model = initial_model().to(dev)
qat_ranges = None  # the int8 file's activation ranges, fixed when quantisation-aware training starts
optimizer = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=weight_decay)
step, trained_s, history, best_psnr = 0, 0.0, [], -math.inf
ckpt_path = out / "ckpt.pt"
if resume and ckpt_path.exists():
    ckpt = torch.load(ckpt_path, map_location="cpu", weights_only=True)
    model.load_state_dict(ckpt["model"])
    optimizer.load_state_dict(ckpt["optimizer"])  # its state moves to the parameters' device
    step, trained_s, history = ckpt["step"], ckpt["trained_s"], ckpt["history"]
    qat_ranges = ckpt.get("qat_ranges")
    best_psnr = max((r["val_psnr"] for r in history), default=-math.inf)
    if master:
        print(f"resumed from {ckpt_path} at step {step} ({trained_s / 60:.1f} min trained)")
if qat and qat_ranges is None:  # the float network's ranges on the int8 file's calibration pool (every rank alike)
    qat_ranges = observe_ranges(model.cpu(), calibration_inputs(h, qat_calibration_count))
    model.to(dev)
trained = QuantSim(model, qat_ranges) if qat else model  # what the loss and the validation see
teacher = initial_model().to(dev).eval().requires_grad_(False) if qat_teacher else None  # init_from's, untrained on
net = torch.nn.parallel.DistributedDataParallel(trained, device_ids=[dev] if use_cuda else None) if ddp else trained
if master:
    print(f"{architecture}: {count_parameters(model)} parameters, {world} process(es) on {dev}"
          + (", bf16 autocast" if bf16 and use_cuda else "") + (f", grown from {init_from}" if init_from else "")
          + (", quantisation-aware (the int8 file's rounding)" if qat else ""))

# ---------------------------------------------------------------------------- data
def cached_pool(name: str, count: int, size: int, pool_seed: int, builder=build_pool) -> list[dict]:
    """A simulated pool, built once (split across the ranks) and cached as an .npz file."""
    if count == 0:
        return []
    version = BURST_POOL_VERSION if builder is build_burst_pool else POOL_VERSION
    path = Path(cache_dir) / f"{name}_h{h}_n{count}_roi{size}_seed{pool_seed}_v{version}.npz"
    if not path.exists():
        part = Path(f"{path}.part{rank}of{world}.npz")
        if not part.exists():
            t0 = time.monotonic()
            save_pool(part, simulate(count, size, pool_seed, range(rank, count, world), builder))
            print(f"rank {rank}: simulated {len(range(rank, count, world))} {name} stacks in {time.monotonic() - t0:.0f} s")
        if ddp:
            dist.barrier()
        if master:
            parts = [load_pool(f"{path}.part{r}of{world}.npz") for r in range(world)]
            pool = [parts[i % world][i // world] for i in range(count)]  # back in index order
            save_pool(path, pool)
            for r in range(world):
                Path(f"{path}.part{r}of{world}.npz").unlink()
        if ddp:
            dist.barrier()
    return load_pool(path)


def simulate(count: int, size: int, pool_seed: int, indices: range, builder=build_pool) -> list[dict]:
    """``builder`` (:func:`build_pool`, or :func:`build_burst_pool`) of ``indices``, over
    ``pool_workers`` processes (the same examples, in order)."""
    if pool_scheduler:  # on a Dask cluster (the [cluster] extra): example i is the same everywhere
        from hbis_torch.cluster.pool import build_pool_on

        return build_pool_on(pool_scheduler, builder, h, count, size, pool_seed, indices)
    if pool_workers <= 1 or len(indices) < 2:
        return builder(h, count, size, pool_seed, indices)
    chunks = [indices[i::pool_workers] for i in range(pool_workers)]
    # fork: the workers need nothing of this script but build_pool (spawn would run it again); one
    # torch thread each, as torch's DataLoader workers: a forked child that enters an OpenMP region
    # of the parent's thread pool can hang (on the GPU machine, the pools of a first try never came)
    with ProcessPoolExecutor(pool_workers, mp_context=multiprocessing.get_context("fork"),
                             initializer=torch.set_num_threads, initargs=(1,)) as pool:
        parts = list(pool.map(builder, *zip(*[(h, count, size, pool_seed, c) for c in chunks])))
    return [parts[i % pool_workers][i // pool_workers] for i in range(len(indices))]


# Training and validation stacks come from disjoint seed streams (seed and seed + 1; the bursts'
# seed + 2 and seed + 3).
train_pool = cached_pool("train", pool_size, pool_roi, seed) + \
    cached_pool("burst", burst_pool_size, burst_roi, seed + 2, build_burst_pool)
val_pool = cached_pool("val", val_size, val_roi, seed + 1) + \
    cached_pool("burstval", burst_val_size, burst_roi, seed + 3, build_burst_pool)
val_set = [whole_example(ex, h) for ex in val_pool[rank::world]]  # split across the ranks


# Every batch comes from its own seed (seed, rank, step), so a resumed run sees the same data
# as an uninterrupted one and the ranks never see the same examples.
def cpu_batch(at_step: int):
    rng = np.random.default_rng([seed, rank, at_step])
    return [torch.from_numpy(a) for a in make_batch(train_pool, h, patch, batch_size, rng)]


_ahead: dict = {}  # step -> future of its batch (prefetch > 0)
_threads = ThreadPoolExecutor(prefetch) if prefetch > 0 else None


def train_batch(at_step: int):
    """The batch of ``at_step`` on the training device; with ``prefetch``, the next ones are
    prepared in threads meanwhile (numpy's crops release the GIL; the GPU waits less)."""
    if _threads is None:
        return [a.to(dev, non_blocking=True) for a in cpu_batch(at_step)]
    for s in range(at_step, at_step + prefetch + 1):
        if s not in _ahead:
            _ahead[s] = _threads.submit(cpu_batch, s)
    return [a.to(dev, non_blocking=True) for a in _ahead.pop(at_step).result()]


@torch.no_grad()
def validate() -> tuple[float, float]:
    """Mean PSNR (dB) over the whole validation set: the network, and the classical image it refines."""
    model.eval()
    sums = torch.zeros(3, dtype=torch.float64)
    for base, noise, truth in val_set:
        base, noise, truth = (torch.from_numpy(a) for a in (base, noise, truth))
        image = trained(base.to(dev), noise.to(dev)).cpu()  # float32 weights, no autocast: the figure of record
        sums += torch.tensor([psnr(image.clamp(0, 1), truth), psnr(depth_to_space(base, h), truth), 1.0],
                             dtype=torch.float64)
    if ddp:
        sums = sums.to(dev)  # NCCL reduces GPU tensors only
        dist.all_reduce(sums)
        sums = sums.cpu()
    model.train()
    return (sums[0] / sums[2]).item(), (sums[1] / sums[2]).item()


def save_checkpoint(path: Path, **extra) -> None:
    state = {"model": model.state_dict(), "optimizer": optimizer.state_dict(), "step": step,
             "trained_s": trained_s, "history": history, "config": config,
             "model_config": architecture.as_dict(), "git_commit": commit, "training_domain": domain,
             **({"qat_ranges": qat_ranges} if qat else {}), **extra}
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def plot_history() -> None:
    from matplotlib.figure import Figure

    minutes = [r["trained_s"] / 60 for r in history]
    fig = Figure(figsize=(6, 4))
    ax = fig.subplots()
    ax.plot(minutes, [r["val_psnr"] for r in history], "o-", ms=3, label="network")
    ax.plot(minutes, [r["base_psnr"] for r in history], "k:", label="classical (the network's input)")
    ax.set_xlabel("training time [min]")
    ax.set_ylabel("validation PSNR [dB]")
    ax.set_title(f"h = {h}, {world} process(es), batch {batch_size} x {world}, patch {patch}")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    with atomic_path(out / "val_psnr.png") as tmp:
        fig.savefig(tmp, format="png", dpi=120)


def crop_loss(image, base_image, truth):
    """The loss of a batch (B, 1, hP, hP).

    ``"db"``: the mean over crops of log(MSE(image) / MSE(classical)), i.e. minus the PSNR gain
    over the classical image (in nepers, 1 = 4.34 dB), so that a clean crop near 60 dB counts as
    much as a noisy one near 30 dB: with a plain L1 the noisy crops dominate the gradient and the
    network learns to disturb the clean ones, which lose dB where the classical image was already
    right. ``loss_floor`` is added to both MSEs: a crop whose classical image is far cleaner than
    it (``1e-5``: 50 dB) hardly counts. ``"l1"``: the plain mean absolute error.
    """
    if loss_kind == "l1":
        return F.l1_loss(image, truth)
    mse = (image - truth).square().mean(dim=(1, 2, 3))
    reference = (base_image - truth).square().mean(dim=(1, 2, 3))
    return (torch.log(mse + loss_floor) - torch.log(reference + loss_floor)).mean()


def learning_rate(progress: float, at_step: int) -> float:
    warm = min(1.0, (at_step + 1) / warmup_steps)
    return lr * warm * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min(progress, 1.0))))


# ---------------------------------------------------------------------------- loop
def train() -> None:
    global step, trained_s, best_psnr
    budget_s = max_minutes * 60
    bar = None
    if master and progress_bar:
        from tqdm import tqdm

        bar = tqdm(total=max_steps, initial=step, desc="train", dynamic_ncols=True)
    started = time.monotonic() - trained_s
    model.train()
    while True:
        # Progress (time or steps, whichever is further) comes from rank 0 so that all ranks
        # agree on the learning rate and on when to stop.
        trained_s = time.monotonic() - started
        progress = torch.tensor([max(step / max_steps if max_steps > 0 else 1.0, trained_s / budget_s)])
        if ddp:
            progress = progress.to(dev)
            dist.broadcast(progress, 0)
            progress = progress.cpu()
        done = progress.item() >= 1.0
        evaluated = bool(history) and history[-1]["step"] == step  # e.g. just resumed
        if (step % eval_interval == 0 or done) and not evaluated:
            val_psnr, base_psnr = validate()
            history.append({"step": step, "trained_s": trained_s, "val_psnr": val_psnr, "base_psnr": base_psnr})
            if master:
                if val_psnr > best_psnr:
                    best_psnr = val_psnr
                    save_checkpoint(out / "model.pt", val_psnr=val_psnr)
                save_checkpoint(ckpt_path)
                record = {"config": config, "git_commit": commit, "history": history}
                atomic_write_text(out / "history.json", json.dumps(record, indent=1))
                plot_history()
                (bar.write if bar else print)(
                    f"step {step}: val PSNR {val_psnr:.2f} dB (classical {base_psnr:.2f}), "
                    f"{trained_s / 60:.1f} min"
                )
        if done:
            break
        for group in optimizer.param_groups:
            group["lr"] = learning_rate(progress.item(), step)
        base, noise, truth = train_batch(step)
        with torch.autocast("cuda", dtype=torch.bfloat16, enabled=bf16 and use_cuda):
            image = net(base, noise)
        if teacher is not None:
            with torch.no_grad():
                truth = teacher(base, noise)
        loss = crop_loss(image.float(), depth_to_space(base, h), truth)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(model.parameters(), grad_clip if grad_clip > 0 else math.inf)
        optimizer.step()
        step += 1
        if bar:
            bar.update(1)
            bar.set_postfix(loss=f"{loss.item():.4f}", grad=f"{grad_norm.item():.2f}", lr=f"{optimizer.param_groups[0]['lr']:.1e}")
    if bar:
        bar.close()
    if master:
        print(f"done: {step} steps, {trained_s / 60:.1f} min, best val PSNR {best_psnr:.2f} dB -> {out / 'model.pt'}")


train()
if ddp:
    # Let every rank finish (rank 0 still writes the last checkpoint), tear the process group
    # down, and leave without Python's finalization. A gloo worker thread can still hold the
    # last reference to the barrier's work object, and freeing it needs the GIL: during
    # finalization that ends the thread inside a C++ destructor, and the rank aborts
    # ("terminate called without an active exception", SIGABRT) after a run that had finished:
    # 2 of 27 tiny two-process runs on 2 busy cores. Everything the run writes is closed by now.
    dist.barrier()
    del net
    dist.destroy_process_group()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)

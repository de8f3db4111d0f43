"""Speed against error of the super-resolution methods, measured side by side in one run.

    python benchmarks/bench_learned.py                 # h with a shipped model; 128^2, 256^2, full frame
    python benchmarks/bench_learned.py --sizes 128 256 # skip the full 960 x 1280 frame

Methods, all on the same simulated stacks (hbis_torch.simulate, 12-bit sensor, exact optics):

- ``bicubic``: the reference frame alone, bicubic upsampling (torch, ``align_corners=False``).
- ``classical``: :func:`hbis_torch.reconstruct.classical.classical_sr` with the optics' cutoff, i.e. what
  ``hbis reconstruct --method classical --registration optics`` computes.
- ``learned-torch``: the classical image refined by the network in eager PyTorch (float32, same
  tiling as below).
- ``learned-onnx``: the exported network in onnxruntime as shipped (:class:`hbis_torch.reconstruct.learned.LearnedSR`,
  provider "auto": the OpenVINO execution provider where this onnxruntime has it).
- ``learned-onnx-cpu``: the same in onnxruntime's own CPU kernels (provider "cpu"; only where the
  shipped provider is another one).

Every method gets the same frames and the same sample positions (from the tracer, via
:func:`hbis_torch.optics.sample_positions`; their cost is reported on its own line, it is shared
by classical and learned). Times are wall-clock medians of
``--repeats`` runs after one warm-up, with 2 threads for torch and onnxruntime alike, glibc's
allocator kept from returning memory (:func:`steady_malloc`: eager torch's best, steady times;
``--default-malloc`` leaves it alone). PSNR is over
the whole output image against the simulator's ground truth (peak 1). Scenes: procedural
(``words``, ``texture``: the kind the network was trained on, new seeds) and photographs from
scikit-image (never seen in training).

``--end-to-end`` times only learned-torch against learned-onnx (the same glue, :func:`super_resolve`),
one call of each in turn; ``--network-only`` the network alone; ``--session-variants`` onnxruntime
settings.

Writes ``benchmarks/results/bench_learned.json``, the Pareto plot ``docs/pareto.png`` and the
markdown table ``benchmarks/results/bench_learned.md`` (copied into docs/learned.md by hand).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from hbis_torch.config import FoveaSystem
from hbis_torch.io_utils import atomic_path
from hbis_torch.provenance import write_results
from hbis_torch.metrics import psnr
from hbis_torch.scan import plan_scan
from hbis_torch.optics import sample_positions
from hbis_torch.simulate import simulate_stack
from hbis_torch.simulate.cases import make_stack, roi_for, scene_cases
from hbis_torch.reconstruct.classical import classical_sr, optics_cutoff
from hbis_torch.reconstruct.learned import (LearnedSR, available_providers, models_dir, noise_params_from_meta,
                                            run_tiled, super_resolve)
from hbis_torch.training.net import HbisSRNet, build_net

REPO = Path(__file__).resolve().parents[1]  # the checkout: default output paths
METHODS = ("bicubic", "classical", "learned-torch", "learned-onnx-cpu", "learned-onnx")
ONNX_METHODS = ("learned-onnx-cpu", "learned-onnx")
THREADS = 2
PAUSE_S = 0.2  # seconds of idle cores before each call timed in turn (timed_in_turn)


def steady_malloc() -> bool:
    """Keep glibc from mapping fresh pages for every large block (True if it took).

    Eager torch allocates each activation anew: 12-57 MB per conv output here. glibc serves such
    blocks with ``mmap`` (fresh pages, zeroed by the kernel on first touch) until its adaptive
    threshold happens to rise above them, so the same torch call ran 66 or 82 ms at 128^2,
    263 or 294-373 ms at 256^2 and 6.2 or 7.3 s on the full frame depending on the process's
    history (h = 4, 256^2 tiles, idle cores), and 512^2 tiles looked 40 % slower than 256^2
    instead of 12 % faster. onnxruntime reuses its own arena and does not care. Serving every
    block from the heap and never trimming it gives torch its best, steady times, so that the
    speed-ups below are not flattered by torch's allocator.
    """
    import ctypes

    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    m_mmap_max, m_trim_threshold = -4, -1  # mallopt parameters (malloc.h)
    return bool(libc.mallopt(m_mmap_max, 0)) and bool(libc.mallopt(m_trim_threshold, 1 << 30))


def timed(fn, repeats: int):
    """(result, median seconds) of ``repeats`` calls after one warm-up call."""
    result = fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return result, float(np.median(times))


def timed_in_turn(fns: dict, repeats: int, warm_up: bool = True):
    """({name: result}, {name: median seconds}, {name: least seconds}): one call of each function
    in turn, ``repeats`` rounds (after one warm-up round), so that a change of load on the cores
    hits all alike. (On shared cores the least time is the one least disturbed by other jobs.)

    Each timed call starts after a pause of ``PAUSE_S``: without it, the worker threads that one
    library leaves spinning after its call (onnxruntime's intra-op pool, torch's OpenMP team)
    take the cores from the next call of the other library (measured, h = 4, 128^2, idle cores:
    torch 89-91 ms instead of 65, onnxruntime 59 instead of 53 ms without the pause).
    """
    results = {name: fn() for name, fn in fns.items()} if warm_up else {}
    times = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            time.sleep(PAUSE_S)
            results[name], seconds = timed_once(fn)
            times[name].append(seconds)
    return (results, {name: float(np.median(t)) for name, t in times.items()},
            {name: float(np.min(t)) for name, t in times.items()})


def shipped_models(hs):
    """(h, onnxruntime runners, eager torch model) for each h in ``hs`` that has a shipped model."""
    for h in hs:
        if (models_dir() / f"hbis_sr_h{h}.onnx").exists():
            yield h, onnx_runners(h), load_torch_model(h)


def onnx_runners(h: int) -> dict[str, LearnedSR]:
    """{"learned-onnx": the shipped provider, "learned-onnx-cpu": onnxruntime's own kernels}; the
    second only where the shipped provider is another one."""
    runners = {"learned-onnx": LearnedSR(h=h, threads=THREADS)}
    if runners["learned-onnx"].provider != "cpu":
        runners["learned-onnx-cpu"] = LearnedSR(h=h, threads=THREADS, provider="cpu")
    return runners


def load_torch_model(h: int) -> HbisSRNet | None:
    path = models_dir() / f"hbis_sr_h{h}.pt"
    if not path.exists():
        return None
    state = torch.load(path, map_location="cpu", weights_only=True)
    model = build_net(state["model_config"])
    model.load_state_dict(state["model"])
    return model.eval()


def run_case(system, h, roi, scene_name, seed, runners, model, repeats, only=METHODS, interleave=False,
             full_repeats: int = 1):
    stack, truth = make_stack(system, h, roi, scene_name, seed)
    frames = stack.to_float()
    positions, t_pos = timed_once(
        lambda: sample_positions(system, stack.phases_deg, stack.reference_index, stack.roi))
    ref = frames[stack.reference_index][None, None]
    rows = {}

    def bicubic():
        return F.interpolate(ref, scale_factor=h, mode="bicubic", align_corners=False)[0, 0].clamp(0, 1).numpy()

    def classical():
        return classical_sr(frames, positions, h, cutoff=optics_cutoff(system), fill_factor=1.0).numpy()

    noise = noise_params_from_meta(stack.meta)  # the simulator records the sensor

    def learned_torch():  # LearnedSR.__call__ with eager torch in place of the session
        def infer(a, b):
            with torch.inference_mode():
                return model(torch.from_numpy(a), torch.from_numpy(b)).numpy()

        shipped = runners["learned-onnx"]
        return super_resolve(lambda a, b: run_tiled(infer, a, b, h, shipped.tile, shipped.halo),
                             classical(), h, noise, cutoff=optics_cutoff(system), views=True)

    methods = {"bicubic": bicubic, "classical": classical}
    if model is not None:
        methods["learned-torch"] = learned_torch
    for name, runner in runners.items():
        # one pass of the network, as the eager-torch column (the h = 7 default averages two)
        methods[name] = lambda runner=runner: runner(classical(), noise, optics_cutoff(system), ensemble=1)
    methods = {name: fn for name, fn in methods.items() if name in only}
    small = roi[2] * roi[3] <= 256 * 256
    if interleave:
        images, times, least = timed_in_turn(methods, repeats if small else full_repeats, warm_up=small)
        for name in methods:
            rows[name] = {"psnr": psnr(images[name], truth), "seconds": times[name], "least_seconds": least[name]}
        return rows, t_pos
    for name, fn in methods.items():
        # Small ROIs: median of repeats after a warm-up; the full frame: one run.
        image, seconds = timed(fn, repeats) if small else timed_once(fn)
        rows[name] = {"psnr": psnr(image, truth), "seconds": seconds}
    return rows, t_pos


def timed_once(fn):
    t0 = time.perf_counter()
    result = fn()
    return result, time.perf_counter() - t0


def summarise(results):
    """Mean PSNR and median time per (h, size, kind, method)."""
    groups = {}
    for r in results:
        for method, m in r["methods"].items():
            key = (r["h"], r["size"], r["kind"], method)
            groups.setdefault(key, []).append(m)
    table = []
    for (h, size, kind, method), ms in sorted(groups.items(), key=lambda kv: (kv[0][0], str(kv[0][1]), kv[0][2], METHODS.index(kv[0][3]))):
        table.append({"h": h, "size": size, "kind": kind, "method": method, "n": len(ms),
                      "psnr": float(np.mean([m["psnr"] for m in ms])),
                      "seconds": float(np.median([m["seconds"] for m in ms]))})
    return table


def markdown(table, positions_s, load):
    lines = [f"Load average during the run (1/5/15 min): {load}", "",
             "| h | ROI (LR px) | scenes | method | PSNR [dB] | time [s] |",
             "| --- | --- | --- | --- | ---: | ---: |"]
    for row in table:
        lines.append(f"| {row['h']} | {row['size']} | {row['kind']} (n={row['n']}) | {row['method']} | "
                     f"{row['psnr']:.2f} | {row['seconds']:.3f} |")
    lines.append("")
    lines.append("Sample positions from the tracer (shared by classical and learned, not in the times above): "
                 + ", ".join(f"{k}: {v:.2f} s" for k, v in positions_s.items()))
    speed = {}
    for row in table:
        speed.setdefault((row["h"], row["size"], row["kind"]), {})[row["method"]] = row["seconds"]
    for method in ONNX_METHODS:
        ratios = [f"{h}/{size}/{kind}: {m['learned-torch'] / m[method]:.2f}x"
                  for (h, size, kind), m in speed.items() if "learned-torch" in m and method in m]
        if ratios:
            lines.append("")
            lines.append(f"{method} speed-up over eager torch (same tiles, same threads): " + ", ".join(ratios))
    return "\n".join(lines) + "\n"


def wide_table(table) -> str:
    """One row per (h, ROI, scenes), one column per method: "PSNR dB, time s"."""
    groups = {}
    for r in table:
        groups.setdefault((r["h"], r["size"], r["kind"], r["n"]), {})[r["method"]] = r
    lines = ["| h | ROI | scenes | " + " | ".join(METHODS) + " |", "| --- | --- | --- |" + " --- |" * len(METHODS)]
    for (h, size, kind, n), methods in groups.items():
        best = max(methods.values(), key=lambda r: r["psnr"])["psnr"]
        cells = []
        for m in METHODS:
            r = methods.get(m)
            if r is None:
                cells.append("-")
                continue
            text = f"{r['psnr']:.2f} dB, {r['seconds']:.3g} s"
            cells.append(f"**{text}**" if r["psnr"] >= best - 0.005 else text)  # ties at 2 decimals
        roi = "960x1280" if size == "full" else f"{size}^2"
        lines.append(f"| {h} | {roi} | {kind} ({n}) | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def pareto_plot(table, path):
    """Time (log) against PSNR; colour = method, marker = ROI size, fill = h."""
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    kinds = sorted({r["kind"] for r in table})
    fig = Figure(figsize=(6 * len(kinds), 4.8))
    axes = fig.subplots(1, len(kinds), squeeze=False)
    colours = {"bicubic": "tab:gray", "classical": "tab:blue", "learned-torch": "tab:orange",
               "learned-onnx-cpu": "tab:purple", "learned-onnx": "tab:red"}
    colours = {m: c for m, c in colours.items() if any(r["method"] == m for r in table)}
    markers = {128: "o", 256: "s", "full": "^"}
    hs = sorted({r["h"] for r in table})
    fills = dict(zip(hs, ("none", "full", "left", "bottom")))
    for ax, kind in zip(axes[0], kinds):
        for row in (r for r in table if r["kind"] == kind):
            colour = colours[row["method"]]
            ax.plot(row["seconds"], row["psnr"], ls="", marker=markers.get(row["size"], "x"), ms=8,
                    color=colour, fillstyle=fills[row["h"]], markeredgewidth=1.5)
        ax.set_xscale("log")
        ax.set_xlabel("time per reconstruction [s] (2 CPU threads)")
        ax.set_ylabel("PSNR [dB]")
        ax.set_title(f"{kind} scenes (up and left is better)")
        ax.grid(alpha=0.3, which="both")
    handles = [Line2D([], [], ls="", marker="o", color=c, label=m) for m, c in colours.items()]
    handles += [Line2D([], [], ls="", marker=mk, color="k", mfc="none", label=f"ROI {sz}") for sz, mk in markers.items()]
    handles += [Line2D([], [], ls="", marker="o", color="k", fillstyle=fills[h], label=f"h = {h}") for h in hs]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    Path(path).chmod(0o644)


def hard_cases() -> str:
    """The hard cases of tests/test_learned_hard_cases.py, learned fp32 vs classical fp64, as a table."""
    from hbis_torch.simulate import EdgesScene, FlatScene, SensorModel

    h, system, roi = 4, FoveaSystem(), (1100, 60, 32, 32)
    plan = plan_scan(system, h)
    positions = sample_positions(system, plan.phases_deg, plan.reference_index, roi).numpy()
    pixel = system.object_pixel_mm
    edges = EdgesScene(size_mm=(40 * pixel, 40 * pixel), normals_deg=(20.0, 110.0),
                       offsets_mm=(0.0, 3 * pixel), levels=(0.1, 0.4, 0.7, 0.95))
    runners = {p: LearnedSR(h=h, threads=THREADS, provider=p) for p in available_providers()}

    def simulate(scene):
        stack, truth = simulate_stack(scene, system, plan, roi=roi, sensor=SensorModel(), seed=3)
        return stack.to_float().numpy(), truth

    base_frames, base_truth = simulate(edges)
    rng = np.random.default_rng(0)
    cases = {
        "normal exposure": (base_frames, base_truth),
        "saturated (frames x 1.6, clipped)": (np.clip(base_frames * 1.6, 0, 1).astype(np.float32),
                                              np.clip(base_truth * 1.6, 0, 1)),
        "near-black (1/200 exposure, 12-bit steps)": ((np.round(base_frames * 0.005 * 4095) / 4095).astype(np.float32),
                                                      base_truth * 0.005),
        "strong noise (+ N(0, 0.05), clipped)": (np.clip(base_frames + rng.normal(0, 0.05, base_frames.shape), 0, 1)
                                                 .astype(np.float32), base_truth),
        "flat 0.5": simulate(FlatScene(size_mm=(1.0, 1.0), level=0.5)),
    }
    lines = ["| case | " + " | ".join(f"learned (fp32, {p})" for p in runners)
             + " | classical (fp64) | largest abs(mean difference) |", "| --- |" + " ---: |" * (len(runners) + 2)]
    for name, (frames, truth) in cases.items():
        measured = []  # the frames' noise, measured on the classical step's lattice (as learned_sr does)
        image = classical_sr(frames, positions, h, cutoff=optics_cutoff(system), noise_params_out=measured).numpy()
        learned = {p: runner(image, measured[0], optics_cutoff(system), ensemble=1) for p, runner in runners.items()}
        reference = classical_sr(torch.from_numpy(frames.astype(np.float64)), torch.from_numpy(positions), h,
                                 cutoff=optics_cutoff(system)).double().clamp(0, 1).numpy()
        scale = max(float(truth.max()), 1e-3)
        worst_mean = max(abs(float(image.mean()) - float(reference.mean())) for image in learned.values())
        lines.append(f"| {name} | " + " | ".join(f"{psnr(image / scale, truth / scale):.2f} dB" for image in learned.values())
                     + f" | {psnr(reference / scale, truth / scale):.2f} dB | {worst_mean:.1e} |")
    return "\n".join(lines) + "\n"


def network_speed(hs, sizes, repeats: int) -> str:
    """Network alone (no input preparation), eager torch against onnxruntime (the shipped provider
    and, where that is another one, onnxruntime's own CPU kernels), same tiles and threads.

    The input content does not change the work, so the inputs are random (seeded). They run in
    turn (see :func:`timed_in_turn`), after one warm-up each.
    """
    cam = FoveaSystem().camera
    lines = []
    for h, runners, model in shipped_models(hs):
        shipped = runners["learned-onnx"]
        if not lines:
            lines = speed_table_head("ROI (LR px)", runners)
        for size_arg in sizes:
            rows, cols = (cam.rows, cam.cols) if size_arg == "full" else (int(size_arg), int(size_arg))
            rng = np.random.default_rng(0)
            frames = rng.random((h * h, rows, cols), dtype=np.float32)  # the classical image's phases
            offsets = rng.random((1, rows, cols), dtype=np.float32)  # the noise map

            def torch_infer(a, b):
                with torch.inference_mode():
                    return model(torch.from_numpy(a), torch.from_numpy(b)).numpy()

            calls = {"learned-torch": lambda: run_tiled(torch_infer, frames, offsets, h, shipped.tile, shipped.halo)}
            calls.update({name: lambda r=runner: r.run_network(frames, offsets) for name, runner in runners.items()})
            _, t, least = timed_in_turn(calls, repeats if size_arg != "full" else 1)
            lines.append(speed_table_row(f"{h} | {size_arg}", t, least, runners))
            print(lines[-1], flush=True)
    return "\n".join(lines) + "\n"


def speed_table_head(what: str, runners) -> list[str]:
    """Head of a table of eager torch against each onnxruntime runner (:func:`speed_table_row`)."""
    names = [name for name in ONNX_METHODS if name in runners]
    cells = ["eager torch [s]"] + [f"{runner_label(runners[n])} [s]" for n in names]
    cells += [f"speed-up, {runner_label(runners[n])}" for n in names]
    cells += [f"(fastest runs, {runner_label(runners[n])})" for n in names]
    return [f"| h | {what} | " + " | ".join(cells) + " |", "|" + " --- |" * (what.count("|") + 2) + " ---: |" * len(cells)]


def speed_table_row(first_cells: str, medians: dict, least: dict, runners) -> str:
    """Median seconds of eager torch and of each runner, then torch's median over each runner's."""
    names = [name for name in ONNX_METHODS if name in runners]
    cells = [f"{medians['learned-torch']:.4f}"] + [f"{medians[n]:.4f}" for n in names]
    cells += [f"{medians['learned-torch'] / medians[n]:.2f}x" for n in names]
    cells += [f"{least['learned-torch'] / least[n]:.2f}x" for n in names]
    return f"| {first_cells} | " + " | ".join(cells) + " |"


def runner_label(runner: LearnedSR) -> str:
    return {"openvino": "ORT OpenVINO EP", "cpu": "ORT CPU EP"}[runner.provider]


def session_variants(h: int, sizes, repeats: int) -> str:
    """onnxruntime session settings side by side, network alone, against eager torch.

    Variants: onnxruntime's CPU kernels with the shipped settings
    (:func:`hbis_torch.reconstruct.learned.session_options`: all graph optimisations, sequential,
    2 intra-op threads with spinning), with no thread spinning, with no memory arena or pattern,
    with the "extended" optimisation level (no NCHWc layout), with IO binding to a preallocated
    output, and the OpenVINO execution provider (where installed, the shipped default). All run
    in turn (:func:`timed_in_turn`), each a whole-ROI pass (one tile); on the full frame the
    shipped 256^2 tiles, and the OpenVINO provider with 512^2 tiles as well.
    """
    import onnxruntime as ort

    from hbis_torch.reconstruct.learned import session_options

    runner, model = LearnedSR(h=h, threads=THREADS, provider="cpu"), load_torch_model(h)
    path = str(runner.path)

    def session(**settings):
        options = session_options(THREADS)
        for key, value in settings.items():
            if key == "config":
                for k, v in value.items():
                    options.add_session_config_entry(k, v)
            else:
                setattr(options, key, value)
        return ort.InferenceSession(path, options, providers=["CPUExecutionProvider"])

    variants = {
        "CPU EP, shipped settings": session(),
        "no spinning": session(config={"session.intra_op.allow_spinning": "0"}),
        "no arena/pattern": session(enable_cpu_mem_arena=False, enable_mem_pattern=False),
        "extended (no NCHWc)": session(graph_optimization_level=ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED),
    }
    openvino = LearnedSR(h=h, threads=THREADS, provider="openvino") if "openvino" in available_providers() else None
    columns = ["eager torch", *variants, "IO binding"]
    columns += ["OpenVINO EP", "OpenVINO EP, 512^2 tiles"] if openvino is not None else []
    lines = ["| ROI (LR px) | " + " | ".join(f"{name} [s]" for name in columns) + " | speed-up, CPU EP | speed-up, OpenVINO EP |",
             "| --- |" + " ---: |" * (len(columns) + 2)]
    cam = FoveaSystem().camera
    for size_arg in sizes:
        rows, cols = (cam.rows, cam.cols) if size_arg == "full" else (int(size_arg), int(size_arg))
        rng = np.random.default_rng(0)
        frames = rng.random((1, h * h, rows, cols), dtype=np.float32)  # the classical image's phases
        offsets = rng.random((1, 1, rows, cols), dtype=np.float32)  # the noise map

        def torch_infer(a, b):
            with torch.inference_mode():
                return model(torch.from_numpy(a), torch.from_numpy(b)).numpy()

        def tiled(infer, tile=runner.tile):
            return lambda: run_tiled(infer, frames[0], offsets[0], h, tile, runner.halo)

        calls = {"eager torch": tiled(torch_infer)}
        for name, sess in variants.items():
            calls[name] = tiled(lambda a, b, sess=sess: sess.run(["image"], {"base": a, "noise": b})[0])
        if size_arg != "full":
            binding = variants["CPU EP, shipped settings"].io_binding()
            out = np.empty((1, 1, h * rows, h * cols), np.float32)
            binding.bind_cpu_input("base", frames)
            binding.bind_cpu_input("noise", offsets)
            binding.bind_output("image", "cpu", 0, np.float32, out.shape, out.ctypes.data)
            calls["IO binding"] = lambda: variants["CPU EP, shipped settings"].run_with_iobinding(binding)
        if openvino is not None:
            calls["OpenVINO EP"] = tiled(openvino.infer)
            if size_arg == "full":
                calls["OpenVINO EP, 512^2 tiles"] = tiled(openvino.infer, 512)
        _, t, _ = timed_in_turn(calls, repeats if size_arg != "full" else 1)
        cells = [f"{t[name]:.3f}" if name in t else "-" for name in columns]
        ov = f"{t['eager torch'] / t['OpenVINO EP']:.2f}x" if "OpenVINO EP" in t else "-"
        lines.append(f"| {size_arg} | " + " | ".join(cells)
                     + f" | {t['eager torch'] / t['CPU EP, shipped settings']:.2f}x | {ov} |")
        print(lines[-1], flush=True)
    return "\n".join(lines) + "\n"


def end_to_end(hs, sizes, repeats: int, full_repeats: int = 1) -> str:
    """learned-torch against the onnxruntime runners only, end to end (the classical image, the
    noise map, tiles, clipping), on the stacks of the main table; one row per stack. They run in turn
    (torch, onnx, torch, onnx, ...), medians of ``repeats`` after a warm-up (the full frame:
    ``full_repeats`` runs each, no warm-up), so that other jobs on the cores slow all alike."""
    system = FoveaSystem()
    lines = []
    for h, runners, model in shipped_models(hs):
        if not lines:
            lines = speed_table_head("ROI | scene", runners)
        for size_arg in sizes:
            size = None if size_arg == "full" else int(size_arg)
            for i, (_, scene) in enumerate(scene_cases(size)):
                rows, _ = run_case(system, h, roi_for(system, size, i), scene, 1000 + i, runners, model, repeats,
                                   only=("learned-torch", *runners), interleave=True, full_repeats=full_repeats)
                for name in runners:
                    assert abs(rows["learned-torch"]["psnr"] - rows[name]["psnr"]) < 0.01
                lines.append(speed_table_row(f"{h} | {size_arg} | {scene}", {k: r["seconds"] for k, r in rows.items()},
                                             {k: r["least_seconds"] for k, r in rows.items()}, runners))
                print(lines[-1], flush=True)
    return "\n".join(lines) + "\n"


def save_side_table(out: Path, name: str, text: str, head: str = "Load") -> str:
    """Write ``text`` to ``out / name`` (atomically) under a line with the load average; return it."""
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    out.mkdir(parents=True, exist_ok=True)
    write_results(out / name, f"{head} average (1/5/15 min): {load}\n\n{text}")
    return text


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hs", type=int, nargs="+", default=[2, 4, 7], help="factors (those with a model)")
    parser.add_argument("--sizes", nargs="+", default=["128", "256", "full"])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--full-repeats", type=int, default=1, help="runs per method on the full frame (--end-to-end)")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    parser.add_argument("--plot", type=Path, default=REPO / "docs" / "pareto.png")
    parser.add_argument("--replot", action="store_true", help="redraw the plot from the saved results and exit")
    parser.add_argument("--network-only", action="store_true",
                        help="only time the network, eager torch against onnxruntime, and exit")
    parser.add_argument("--session-variants", action="store_true",
                        help="only compare onnxruntime session settings (h = 4 unless --hs) and exit")
    parser.add_argument("--end-to-end", action="store_true",
                        help="only time learned-torch against learned-onnx end to end and exit")
    parser.add_argument("--default-malloc", action="store_true",
                        help="leave glibc's allocator as it is (see steady_malloc; torch's times then vary)")
    parser.add_argument("--hard-cases", action="store_true",
                        help="only print the hard-case table (learned fp32 vs classical fp64) and exit")
    args = parser.parse_args(argv)
    torch.set_num_threads(THREADS)
    if not args.default_malloc and not steady_malloc():
        print("could not set glibc's malloc options; torch's times may vary by 10-40 %")
    if args.hard_cases:
        print(hard_cases())
        return 0
    if args.replot:
        table = json.loads((args.out / "bench_learned.json").read_text())["table"]
        pareto_plot(table, args.plot)
        print(wide_table(table))
        return 0
    if args.session_variants:
        h = args.hs[0] if len(args.hs) == 1 else 4
        print(save_side_table(args.out, "bench_learned_session.md", session_variants(h, args.sizes, args.repeats),
                              f"h = {h}, load"))
        return 0
    if args.end_to_end:
        print(save_side_table(args.out, "bench_learned_e2e.md",
                              end_to_end(args.hs, args.sizes, args.repeats, args.full_repeats)))
        return 0
    if args.network_only:
        print(save_side_table(args.out, "bench_learned_network.md", network_speed(args.hs, args.sizes, args.repeats)))
        return 0
    system = FoveaSystem()
    results, positions_s = [], {}
    for h in args.hs:
        if not (models_dir() / f"hbis_sr_h{h}.onnx").exists():
            print(f"h = {h}: no model, skipped")
            continue
        runners, model = onnx_runners(h), load_torch_model(h)
        for size_arg in args.sizes:
            size = None if size_arg == "full" else int(size_arg)
            for i, (kind, scene) in enumerate(scene_cases(size)):
                roi = roi_for(system, size, i)
                t0 = time.perf_counter()
                rows, t_pos = run_case(system, h, roi, scene, 1000 + i, runners, model, args.repeats)
                label = "full" if size is None else size
                positions_s[f"h{h} {label}"] = t_pos
                results.append({"h": h, "size": label, "kind": kind, "scene": scene, "roi": list(roi), "methods": rows})
                summary = ", ".join(f"{k} {v['psnr']:.2f} dB {v['seconds']:.3f} s" for k, v in rows.items())
                print(f"h={h} {label} {scene} @ {roi[:2]}: {summary} [{time.perf_counter() - t0:.0f} s]", flush=True)
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    table = summarise(results)
    args.out.mkdir(parents=True, exist_ok=True)
    write_results(args.out / "bench_learned.json",
                  {"load_average": load, "results": results, "table": table, "positions_s": positions_s}, argv=argv)
    text = markdown(table, positions_s, load) + "\n" + wide_table(table)
    write_results(args.out / "bench_learned.md", text, argv=argv)
    pareto_plot(table, args.plot)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Every speed goal of the [fast] issue, as ratios measured side by side in one run.

    python benchmarks/bench_fast.py                 # h = 4 and 7, best of 3
    python benchmarks/bench_fast.py --quick         # h = 4 only, best of 2, 20 stacks for --out-dir
    python benchmarks/bench_fast.py --skip fullframe outdir

Each goal compares a time with work that fixes its floor on the same machine, in the same run;
every measurement is repeated ``--repeats`` times, in turn with the others, and the best kept
(other jobs on shared cores only ever slow a run down):

- ``fft``: one float32 FFT pair (``torch.fft.rfft2`` + ``irfft2``, 2 threads) of the full-frame
  output (960 h x 1280 h): the floor of any Wiener step.
- ``fullframe``: ``hbis reconstruct`` (a fresh process, as a user runs it) of a full 960 x 1280
  frame of ``hbis simulate --scene camera --roi full`` and of a 32 x 32 stack; the method's own
  time is the difference (start-up and fixed costs cancel), over the FFT pair
  (goals: classical <= 6, learned <= 9; the learned method with ``--precision bf16`` too, where
  this CPU runs bf16). Peak RSS of the full-frame process (``wait4``; goal
  <= 1 GB at h = 4, 2 GB at h = 7).
- ``network``: the h = 4 network alone on a 480 x 640 LR input: onnxruntime fp32 and int8 (the
  shipped ``.int8.onnx``), and OpenVINO fp32, int8 and bf16 (``--precision bf16``, on CPUs with
  bf16 units) where the ``openvino`` package is installed (goal: the faster int8 runtime >= 2.5 x
  onnxruntime fp32). Beside it, one of the network's body convolutions alone in onnxruntime's
  float32 and integer kernels: the most onnxruntime's int8 gains on this CPU, which depends on its
  int8 instruction sets (VNNI, AMX; printed beside it).
- ``startup``: a 32 x 32 learned reconstruct against ``python -c "import torch"`` (goal <= 1.3),
  with the default provider and with ``--provider cpu`` (both onnxruntime's kernels since
  ``auto`` runs them: the two rows show the run's noise).
- ``outdir``: N stacks of 64 x 64 at h = 4 through one ``hbis reconstruct --out-dir`` against
  separate invocations, of which ``--separate`` are run and the time scaled to N (goal >= 5).

Prints one table of goals and writes it to ``--out`` (default
benchmarks/results/bench_fast.md) with the machine's load.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PARTS = ("fft", "fullframe", "network", "startup", "outdir")


def env() -> dict:
    return {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""),
            "HBIS_PROGRESS": "0"}


def run_process(argv: list[str]) -> tuple[float, float]:
    """(wall seconds, peak RSS in GB) of one child process; raises if it fails."""
    t0 = time.perf_counter()
    child = subprocess.Popen(argv, cwd=REPO, env=env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(child.pid, 0)
    wall = time.perf_counter() - t0
    if os.waitstatus_to_exitcode(status) != 0:
        raise RuntimeError(f"{' '.join(argv)} failed: {child.stderr.read().decode()[-2000:]}")
    child.stderr.close()
    return wall, usage.ru_maxrss / 2**20


def hbis(*args: str) -> list[str]:
    return [sys.executable, "-m", "hbis_torch", *args]


def simulate(work: Path, h: int, roi: str, name: str) -> Path:
    path = work / name
    if not path.exists():
        run_process(hbis("simulate", "--scene", "camera", "--h", str(h), "--roi", roi, "--out", str(path)))
    return path


def fft_pair(h: int, repeats: int) -> float:
    """Best time of one float32 rfft2 + irfft2 of the (960 h, 1280 h) output, 2 threads."""
    import torch

    torch.set_num_threads(2)
    x = torch.rand(960 * h, 1280 * h)
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        torch.fft.irfft2(torch.fft.rfft2(x), s=x.shape)
        best = min(best, time.perf_counter() - t0)
    return best


def fullframe(work: Path, h: int, repeats: int) -> dict:
    """Own times (full frame minus 32 x 32, best of ``repeats``) and peak RSS, per method (and the
    learned method with ``--precision bf16`` where this CPU runs it)."""
    full = simulate(work, h, "full", f"full_h{h}.tif")
    small = simulate(work, h, "624,464,32,32", f"small_h{h}.tif")
    from hbis_torch.reconstruct.learned.runtime import bf16_available

    methods = {"classical": ["--method", "classical"], "learned": ["--method", "learned"]}
    if bf16_available():
        methods["learned bf16"] = ["--method", "learned", "--precision", "bf16"]
    best: dict = {}
    for _ in range(repeats):
        for method, options in methods.items():
            for size, stack in (("full", full), ("small", small)):
                out = work / f"out_{method.replace(' ', '_')}_{size}_h{h}.tif"
                wall, rss = run_process(hbis("reconstruct", str(stack), *options, "--out", str(out), "--overwrite"))
                key = (method, size)
                best[key] = min(best.get(key, (float("inf"), 0)), (wall, rss))
    return {method: {"full_s": best[method, "full"][0], "small_s": best[method, "small"][0],
                     "own_s": best[method, "full"][0] - best[method, "small"][0],
                     "peak_rss_gb": best[method, "full"][1]} for method in methods}


def network(repeats: int) -> dict:
    """Best seconds of the h = 4 network on a 480 x 640 LR input, per runtime and precision."""
    import numpy as np

    from hbis_torch.reconstruct.learned import LearnedSR
    from hbis_torch.reconstruct.learned.runtime import openvino_installed

    from hbis_torch.training.data import build_pool, whole_example

    # a training-pool stack's inputs, tiled to 480 x 640: values as the network meets them (its
    # int8 ranges are fixed, so random values would make the rms change meaningless)
    base, noise, _ = whole_example(build_pool(4, 1, 80, seed=99)[0], 4)
    feeds = {"base": np.ascontiguousarray(np.tile(base, (1, 1, 6, 8))),
             "noise": np.ascontiguousarray(np.tile(noise, (1, 1, 6, 8)))}
    # the product's own sessions (LearnedSR), as --provider and --precision choose them
    runners = {"onnxruntime fp32": LearnedSR(h=4, provider="cpu", precision="fp32").session,
               "onnxruntime int8": LearnedSR(h=4, provider="cpu", precision="int8").session}
    if openvino_installed():
        runners["OpenVINO fp32"] = LearnedSR(h=4, provider="openvino", precision="fp32").session
        runners["OpenVINO int8"] = LearnedSR(h=4, provider="openvino", precision="int8").session
        bf16 = LearnedSR(h=4, precision="bf16")
        if bf16.precision == "bf16":  # else this CPU has no bf16 units (the note says so)
            runners["OpenVINO bf16"] = bf16.session
        else:
            print(f"OpenVINO bf16: not run ({bf16.note})")
    reference = runners["onnxruntime fp32"].run(["image"], feeds)[0]
    times, change = {}, {}
    for _ in range(repeats):
        for name, runner in runners.items():
            t0 = time.perf_counter()
            out = np.asarray(runner.run(["image"], feeds)[0])
            times[name] = min(times.get(name, float("inf")), time.perf_counter() - t0)
            change[name] = float(np.sqrt(np.mean((out - reference) ** 2)))
    return {name: {"seconds": times[name], "rms_change": change[name]} for name in runners}


def int8_ceiling(repeats: int) -> dict:
    """Best seconds of one of the network's body convolutions alone (32 -> 32 channels, 3 x 3, a
    480 x 640 LR input, 2 threads) in onnxruntime's float32 ``Conv`` and its integer ``QLinearConv``
    (uint8 activations, int8 weights, as the int8 files run): their ratio bounds what any int8
    network of this design gains on this CPU, whatever its quantisation."""
    import numpy as np
    import onnxruntime as ort
    from onnx import TensorProto, helper, numpy_helper

    rng = np.random.default_rng(0)
    weights = rng.normal(0, 0.1, (32, 32, 3, 3)).astype(np.float32)
    shape = [1, 32, 480, 640]

    def model(integer: bool) -> bytes:
        kind = TensorProto.UINT8 if integer else TensorProto.FLOAT
        if integer:  # any scales do: the integer kernel's time does not depend on them
            arrays = {"w": np.clip(np.round(weights / 0.01), -127, 127).astype(np.int8),
                      "xs": np.float32(0.02), "xz": np.uint8(128), "ws": np.full(32, 0.01, np.float32),
                      "wz": np.zeros(32, np.int8), "ys": np.float32(0.05), "yz": np.uint8(128)}
            node = helper.make_node("QLinearConv", ["x", "xs", "xz", "w", "ws", "wz", "ys", "yz"], ["y"],
                                    pads=[1, 1, 1, 1])
        else:
            arrays = {"w": weights}
            node = helper.make_node("Conv", ["x", "w"], ["y"], pads=[1, 1, 1, 1])
        graph = helper.make_graph([node], "conv", [helper.make_tensor_value_info("x", kind, shape)],
                                  [helper.make_tensor_value_info("y", kind, shape)],
                                  [numpy_helper.from_array(np.asarray(v), k) for k, v in arrays.items()])
        return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], ir_version=9).SerializeToString()

    options = ort.SessionOptions()
    options.intra_op_num_threads = 2
    best = {}
    for name, integer in (("fp32", False), ("int8", True)):
        session = ort.InferenceSession(model(integer), options, providers=["CPUExecutionProvider"])
        x = rng.integers(0, 256, shape).astype(np.uint8) if integer else rng.random(shape, dtype=np.float32)
        session.run(None, {"x": x})
        for _ in range(max(repeats, 10)):  # 0.02-0.04 s each
            t0 = time.perf_counter()
            session.run(None, {"x": x})
            best[name] = min(best.get(name, float("inf")), time.perf_counter() - t0)
    return best


def cpu_flags() -> str:
    """The CPU's instruction sets that int8 inference depends on, from /proc/cpuinfo (Linux)."""
    try:
        flags = next(line for line in Path("/proc/cpuinfo").read_text().splitlines() if line.startswith("flags"))
    except (OSError, StopIteration):
        return "unknown"
    have = set(flags.split(":", 1)[1].split())
    wanted = ("avx2", "avx512f", "avx512_vnni", "avx_vnni", "amx_int8")
    return ", ".join(f"{f} {'yes' if f in have else 'no'}" for f in wanted)


def startup(work: Path, repeats: int) -> dict:
    small = simulate(work, 4, "624,464,32,32", "small_h4.tif")
    best = {"torch": float("inf"), "learned_32": float("inf"), "learned_32_cpu": float("inf")}
    for _ in range(repeats):
        best["torch"] = min(best["torch"], run_process([sys.executable, "-c", "import torch"])[0])
        for key, extra in (("learned_32", []), ("learned_32_cpu", ["--provider", "cpu"])):
            best[key] = min(best[key], run_process(hbis("reconstruct", str(small), "--method", "learned", *extra,
                                                        "--out", str(work / "start.tif"), "--overwrite"))[0])
    return best


def outdir(work: Path, count: int, separate: int, repeats: int) -> dict:
    """Seconds per stack: ``count`` stacks through --out-dir, and ``separate`` separate invocations."""
    stack = simulate(work, 4, "608,448,64,64", "s64_h4.tif")
    folder = work / "many"
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir()
    for i in range(count):
        shutil.copy(stack, folder / f"s{i:03d}.tif")
    batch, single = float("inf"), float("inf")
    for r in range(repeats):
        out = work / f"many_out_{r}"
        shutil.rmtree(out, ignore_errors=True)
        batch = min(batch, run_process(hbis("reconstruct", str(folder / "*.tif"), "--method", "learned",
                                            "--out-dir", str(out)))[0] / count)
        t0 = time.perf_counter()
        for i in range(separate):
            run_process(hbis("reconstruct", str(folder / f"s{i:03d}.tif"), "--method", "learned",
                             "--out", str(work / f"one_{i}.tif"), "--overwrite"))
        single = min(single, (time.perf_counter() - t0) / separate)
    return {"count": count, "separate": separate, "batch_s_per_stack": batch, "single_s_per_stack": single}


def report(results: dict, hs, args) -> str:
    """The goals table (markdown)."""
    rows = []

    def row(goal, value, target, met, detail):
        rows.append(f"| {goal} | {value} | {target} | {'yes' if met else '**no**'} | {detail} |")

    for h in hs:
        if ("fft", h) in results and ("fullframe", h) in results:
            fft, ff = results["fft", h], results["fullframe", h]
            for method, target in (("classical", 6), ("learned", 9), ("learned bf16", 9)):
                if method not in ff:
                    continue
                r = ff[method]["own_s"] / fft
                row(f"{method} own time / FFT pair, h = {h}", f"{r:.1f}x", f"<= {target}x", r <= target,
                    f"full {ff[method]['full_s']:.2f} s - 32² {ff[method]['small_s']:.2f} s; FFT pair {fft:.3f} s")
            rss = max(ff[m]["peak_rss_gb"] for m in ff)
            limit = 1.0 if h == 4 else 2.0
            row(f"peak RSS, full frame, h = {h}", f"{rss:.2f} GB", f"<= {limit:.0f} GB", rss <= limit,
                ", ".join(f"{m} {ff[m]['peak_rss_gb']:.2f} GB" for m in ff))
    if "network" in results:
        net = results["network"]
        fp32 = net["onnxruntime fp32"]["seconds"]
        int8 = min((v["seconds"], k) for k, v in net.items() if "int8" in k)
        row("int8 network speed / fp32 (h = 4, 480 x 640 LR; the faster int8 runtime against onnxruntime fp32)",
            f"{fp32 / int8[0]:.2f}x", ">= 2.5x", fp32 / int8[0] >= 2.5,
            f"{int8[1]}; " + "; ".join(f"{k} {v['seconds']:.3f} s (rms change {v['rms_change']:.1e})"
                                       for k, v in net.items()))
        if "OpenVINO bf16" in net:
            r = fp32 / net["OpenVINO bf16"]["seconds"]
            row("bf16 network speed / fp32 (--precision bf16; not a goal of the issue)", f"{r:.2f}x", "-", True,
                f"OpenVINO bf16 {net['OpenVINO bf16']['seconds']:.3f} s against onnxruntime fp32 {fp32:.3f} s")
    if "ceiling" in results:
        c = results["ceiling"]
        r = c["fp32"] / c["int8"]
        row("int8 / fp32, one body convolution alone in onnxruntime (the most its int8 kernels gain here)", f"{r:.2f}x",
            ">= 2.5x", r >= 2.5, f"Conv {c['fp32']:.4f} s, QLinearConv {c['int8']:.4f} s, 32 -> 32 channels, "
            f"3 x 3, 480 x 640, onnxruntime's CPU kernels; this CPU: {cpu_flags()}")
    if "startup" in results:
        s = results["startup"]
        r = s["learned_32"] / s["torch"]
        row("32² learned reconstruct / import torch", f"{r:.2f}x", "<= 1.3x", r <= 1.3,
            f"{s['learned_32']:.2f} s against {s['torch']:.2f} s; with --provider cpu (the default's path "
            f"too; their difference is the run's noise) {s['learned_32_cpu']:.2f} s = {s['learned_32_cpu'] / s['torch']:.2f}x")
    if "outdir" in results:
        o = results["outdir"]
        r = o["single_s_per_stack"] / o["batch_s_per_stack"]
        row(f"--out-dir throughput / separate invocations ({o['count']} stacks of 64², h = 4)", f"{r:.1f}x",
            ">= 5x", r >= 5, f"{o['batch_s_per_stack']:.3f} s a stack in one process; "
            f"{o['single_s_per_stack']:.2f} s a stack over {o['separate']} separate invocations, scaled")
    load = os.getloadavg()
    return (f"# bench_fast: the [fast] goals, measured side by side\n\n`python benchmarks/bench_fast.py "
            f"{' '.join(args.argv)}`, best of {args.repeats}, {len(os.sched_getaffinity(0))} CPUs, load average "
            f"{load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f} at the end (shared cores: other jobs slow "
            f"every figure, ratios less)\n\n| goal | measured | target | met | detail |\n| --- | --- | --- | --- | --- |\n"
            + "\n".join(rows) + "\n")


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="h = 4 only, best of 2, 20 stacks, 3 separate runs")
    parser.add_argument("--hs", type=int, nargs="+", default=None, choices=(4, 7))
    parser.add_argument("--repeats", type=int, default=None)
    parser.add_argument("--stacks", type=int, default=None, help="stacks through --out-dir (default 100)")
    parser.add_argument("--separate", type=int, default=None, help="separate invocations run (default 10)")
    parser.add_argument("--skip", nargs="+", default=[], choices=PARTS)
    parser.add_argument("--work", type=Path, default=None, help="folder for the stacks (default: a temporary one)")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "bench_fast.md")
    args = parser.parse_args(argv)
    args.argv = argv
    hs = args.hs or ([4] if args.quick else [4, 7])
    args.repeats = args.repeats or (2 if args.quick else 3)
    count = args.stacks or (20 if args.quick else 100)
    separate = args.separate or (3 if args.quick else 10)
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_fast_"))
    work.mkdir(parents=True, exist_ok=True)
    results: dict = {}
    for h in hs:
        if "fft" not in args.skip:
            results["fft", h] = fft_pair(h, args.repeats)
        if "fullframe" not in args.skip:
            results["fullframe", h] = fullframe(work, h, args.repeats)
    if "network" not in args.skip:
        results["network"] = network(args.repeats)
        results["ceiling"] = int8_ceiling(args.repeats)
    if "startup" not in args.skip:
        results["startup"] = startup(work, args.repeats)
    if "outdir" not in args.skip:
        results["outdir"] = outdir(work, count, separate, args.repeats)
    text = report(results, hs, args)
    print(text)
    from hbis_torch.provenance import write_results

    write_results(args.out, text, argv=argv)
    if args.work is None:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

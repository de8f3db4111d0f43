"""Time one ONNX SR model in one onnxruntime execution provider, in whatever onnxruntime is installed.

Needs only numpy and onnxruntime, so that onnxruntime builds that cannot share an environment
(``onnxruntime`` and ``onnxruntime-openvino`` install the same module) can be compared by running
this script from each environment in turn:

    /path/to/ort131-venv/bin/python benchmarks/time_onnx_session.py hbis_torch/models/hbis_sr_h4.onnx --provider cpu
    python benchmarks/time_onnx_session.py hbis_torch/models/hbis_sr_h4.onnx --provider openvino

The session settings are those of :func:`hbis_torch.reconstruct.learned.session_options` and
:func:`~hbis_torch.reconstruct.learned.execution_providers` (written out here, since the package is not
importable from a bare environment). Prints one JSON line: onnxruntime version, provider, median
and least milliseconds of ``--repeats`` runs after a warm-up, each after a 0.2 s pause.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import onnxruntime as ort


def session(path: str, provider: str, threads: int) -> ort.InferenceSession:
    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    providers = ["CPUExecutionProvider"]
    if provider == "openvino":
        settings = {"device_type": "CPU", "precision": "FP32", "num_of_threads": str(threads)}
        providers.insert(0, ("OpenVINOExecutionProvider", settings))
    return ort.InferenceSession(path, options, providers=providers)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", help="an hbis SR .onnx file")
    parser.add_argument("--provider", choices=("cpu", "openvino"), default="cpu")
    parser.add_argument("--size", type=int, default=256, help="LR side of the square input (one pass)")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    sess = session(args.model, args.provider, args.threads)
    h = int(sess.get_modelmeta().custom_metadata_map["h"])
    rng = np.random.default_rng(0)
    feeds = {"frames": rng.random((1, h * h, args.size, args.size), dtype=np.float32),
             "offsets": (rng.random((1, 2 * h * h, args.size, args.size), dtype=np.float32) - 0.5) * 0.5}
    sess.run(None, feeds)
    times = []
    for _ in range(args.repeats):
        time.sleep(0.2)
        t0 = time.perf_counter()
        sess.run(None, feeds)
        times.append(time.perf_counter() - t0)
    print(json.dumps({"onnxruntime": ort.__version__, "provider": args.provider, "h": h, "size": args.size,
                      "median_ms": round(1e3 * float(np.median(times)), 1), "least_ms": round(1e3 * min(times), 1)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Scale-out on Dask (hbis_torch.cluster): a LocalCluster of 2 worker processes, small stacks.

The same outputs bit for bit as the in-process paths; a worker killed mid-write costs no output
and duplicates none; a corrupt input among good ones; a rerun that skips what is done; a lost
scheduler (exit 3, then a rerun resumes); a training pool equal to the local one.
"""

import hashlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import tifffile

distributed = pytest.importorskip("distributed")

from hbis_torch.cli import main  # noqa: E402
from hbis_torch.cluster.engine import parse_scheduler, publish, run_task, run_tasks  # noqa: E402
from hbis_torch.errors import HbisInputError  # noqa: E402
from hbis_torch.stack_io import read_stack  # noqa: E402


@pytest.fixture(scope="module")
def cluster():
    """One LocalCluster for the module: 2 worker processes of one thread (as `--scheduler local:2`)."""
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                                  silence_logs=40) as local:
        yield local.scheduler_address


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """Three different small scan stacks (h = 2, 32 x 32 px: registrable), two bursts (multi-page TIFFs) and the burst
    stacks assembled from them."""
    from hbis_torch.config import FoveaSystem
    from hbis_torch.scan import plan_scan
    from hbis_torch.simulate import SceneSpec, load_scene, simulate_stack
    from hbis_torch.simulate.burst import random_motions, simulate_burst
    from hbis_torch.stack_io import write_stack

    folder = tmp_path_factory.mktemp("inputs")
    system = FoveaSystem()
    pixel = system.object_pixel_mm
    spec = SceneSpec(size_mm=(32 * pixel * 1.25,) * 2, pixel_mm=pixel, detail_mm=pixel / 16)
    scans = []
    for seed in (1, 2, 3):
        stack, _ = simulate_stack(load_scene("words", spec, seed=seed), system, plan_scan(system, 2),
                                  roi=(600, 400, 32, 32), seed=seed)
        scans.append(folder / f"scan{seed}.tif")
        write_stack(scans[-1], stack)
    from skimage import data, transform

    truth = transform.resize(data.camera().astype(float) / 255, (48, 48), anti_aliasing=True)
    from hbis_torch.capture.burst import assemble_burst

    bursts, burst_stacks = [], []
    for seed in (1, 2):
        motions = random_motions(5, (24, 24), np.random.default_rng(seed), 1.5, 1.0)
        burst = simulate_burst(truth, 2, motions, noise=0.005, seed=seed)
        bursts.append(folder / f"clip{seed}.tif")
        tifffile.imwrite(bursts[-1], burst.frames, photometric="minisblack")
        burst_stacks.append(folder / f"burst{seed}.tif")
        write_stack(burst_stacks[-1], assemble_burst(burst.frames, 2)[0])
    corrupt = folder / "corrupt.tif"
    corrupt.write_bytes(b"II*\x00 truncated")
    return {"scans": scans, "bursts": bursts, "burst_stacks": burst_stacks, "corrupt": corrupt}


def _tree(folder: Path) -> dict:
    """Every output file's SHA-256, by name: equal trees are equal byte for byte."""
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir()) if p.name != ".lock"}


def test_reconstruct_on_the_cluster_is_bit_identical_names_the_corrupt_one_and_resumes(cluster, inputs, tmp_path,
                                                                                         capsys):
    stacks = [str(p) for p in inputs["scans"] + inputs["burst_stacks"]]  # HBIS scans and bursts, registered
    here, again, there = tmp_path / "here", tmp_path / "again", tmp_path / "there"
    for folder in (here, again):  # in this process (stacks side by side on threads), twice
        assert main(["-q", "reconstruct", *stacks, "--out-dir", str(folder)]) == 0
    capsys.readouterr()
    code = main(["-q", "reconstruct", *stacks, str(inputs["corrupt"]), "--out-dir", str(there),
                 "--scheduler", cluster])
    out, err = capsys.readouterr()
    assert code == 2, err  # the corrupt stack: bad input, and only that
    assert len(_tree(here)) == 5 and _tree(there) == _tree(here) == _tree(again)  # bit for bit, nothing more
    assert "reconstructed 5 of 6 stacks" in out and f"exit 2: {inputs['corrupt']}" in out
    assert len([line for line in err.splitlines() if str(inputs["corrupt"]) in line]) == 1
    for folder, where in ((there, ["--scheduler", cluster]), (here, [])):  # a rerun resumes, with or without Dask
        before = {p.name: p.stat().st_ino for p in folder.iterdir()}
        (folder / "scan2.classical.tif").unlink()  # as if the run had stopped before this one
        code = main(["-q", "reconstruct", *stacks, "--out-dir", str(folder), *where])
        out = capsys.readouterr().out
        assert code == 0 and "reconstructed 1 of 5 stacks" in out and "4 done before, skipped" in out, out
        assert _tree(folder) == _tree(again)
        after = {p.name: p.stat().st_ino for p in folder.iterdir()}
        assert all(after[n] == before[n] for n in after if n not in (".lock", "scan2.classical.tif"))  # not rewritten
    for where in (["--scheduler", cluster], []):  # --overwrite replaces, with or without Dask
        (here / "scan1.classical.tif").write_bytes(b"old")
        code = main(["-q", "reconstruct", *stacks, "--out-dir", str(here), "--overwrite",
                     *where])
        assert code == 0 and "reconstructed 5 of 5 stacks" in capsys.readouterr().out
        assert _tree(here) == _tree(again)


def test_a_raw_burst_on_the_cluster_writes_what_the_in_process_batch_writes(cluster, tmp_path, capsys):
    pytest.importorskip("rawpy")
    pytest.importorskip("pidng")
    pytest.importorskip("cv2")
    from dng_bursts import write_dng_burst

    frames = write_dng_burst(tmp_path, size=48)
    stack = tmp_path / "raw.tif"
    assert main(["-q", "assemble", "--burst", "--scale", "2", "--out", str(stack), *frames]) == 0
    here, there = tmp_path / "here", tmp_path / "there"
    assert main(["-q", "reconstruct", str(stack), "--out-dir", str(here)]) == 0
    assert main(["-q", "reconstruct", str(stack), "--out-dir", str(there), "--scheduler", cluster]) == 0
    # the linear 16-bit TIFF and its sRGB preview, byte for byte
    assert sorted(_tree(there)) == ["raw.classical.preview.png", "raw.classical.tif"] and _tree(there) == _tree(here)
    for folder, where in ((here, []), (there, ["--scheduler", cluster])):  # a preview left alone: refused, kept
        (folder / "raw.classical.tif").unlink()
        (folder / "raw.classical.preview.png").write_bytes(b"keep me")
        capsys.readouterr()
        assert main(["-q", "reconstruct", str(stack), "--out-dir", str(folder), *where]) == 2
        assert "exists already" in capsys.readouterr().err
        assert (folder / "raw.classical.preview.png").read_bytes() == b"keep me"


@pytest.fixture
def one_thread():
    """torch on one thread, as each task on a worker: a burst's motions are sums that torch splits
    across its threads, so their last bits depend on the thread count (1e-7 px); the single
    commands of the test run in this process."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def test_bursts_and_validate_many_match_one_at_a_time(cluster, inputs, tmp_path, capsys, one_thread):
    bursts = [str(p) for p in inputs["bursts"]]
    there, here, one = tmp_path / "there", tmp_path / "here", tmp_path / "one"
    one.mkdir()
    for path in inputs["bursts"]:  # today's path: one command per burst
        assert main(["-q", "assemble", "--burst", "--scale", "2", "--out", str(one / f"{path.stem}.burst.tif"),
                     str(path)]) == 0
    assert main(["-q", "assemble", "--burst", "--scale", "2", *bursts, "--out-dir", str(there),
                 "--scheduler", "local:2"]) == 0
    assert main(["-q", "assemble", "--burst", "--scale", "2", *bursts, "--out-dir", str(here)]) == 0
    # Byte for byte: one command per burst, the in-process --out-dir and the Dask workers
    # (torch.linalg.lstsq's default driver once made a burst's gain differ in its last bits from
    # run to run: hbis_torch.capture.brightness.LSTSQ_DRIVER).
    assert len(_tree(one)) == 2 and _tree(one) == _tree(there) == _tree(here)
    capsys.readouterr()
    stacks = [str(p) for p in sorted(there.glob("*.burst.tif"))]
    options = ["--method", "single-frame,classical", "--holdout", "1"]
    assert main(["-q", "validate", stacks[0], "--json", *options]) == 0
    single = json.loads(capsys.readouterr().out)
    scores, here = tmp_path / "scores", tmp_path / "scores-here"
    assert main(["-q", "validate", *stacks, *options, "--out-dir", str(scores), "--scheduler", cluster]) == 0
    assert main(["-q", "validate", *stacks, *options, "--out-dir", str(here)]) == 0  # the same engine, here

    def untimed(path):
        report = json.loads(path.read_text())
        for method in report["methods"].values():
            method.pop("seconds")
        return report

    assert sorted(p.name for p in scores.glob("*.json")) == ["clip1.validate.json", "clip2.validate.json"]
    assert untimed(scores / "clip1.validate.json") == {**single, "methods": {
        name: {k: v for k, v in m.items() if k != "seconds"} for name, m in single["methods"].items()}}
    assert {p.name: untimed(p) for p in here.glob("*.json")} == {p.name: untimed(p) for p in scores.glob("*.json")}


class KillOnce:
    """A job that, the first time it runs anywhere (a marker file), writes half its staging file
    and kills its own worker process with SIGKILL: a worker lost mid-write."""

    def __init__(self, job, marker):
        self.job, self.marker = job, str(marker)

    def __call__(self, source, staging):
        try:
            fd = os.open(self.marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            return self.job(source, staging)
        os.write(fd, f"{source}\n".encode())
        os.close(fd)
        Path(staging).write_bytes(b"II*\x00half a file")
        os.kill(os.getpid(), signal.SIGKILL)


def test_a_worker_killed_mid_write_costs_no_output_and_duplicates_none(cluster, inputs, tmp_path):
    import cloudpickle

    from hbis_torch.cli import build_parser
    from hbis_torch.cli.cmd_reconstruct import prepare, reconstruct_one
    from hbis_torch.cli.jobs import ReconstructJob, plain_args

    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the workers cannot import this file
    args = build_parser().parse_args(["reconstruct", "x", "--out-dir", str(tmp_path), "--registration", "optics"])
    job = ReconstructJob(plain_args(args), prepare(args), threads=1, reconstruct_one=reconstruct_one)
    sources = inputs["scans"] * 2  # six tasks, three outputs twice over: each published once
    outs = [tmp_path / "out" / f"{p.stem}.{k}.tif" for k in (0, 1) for p in inputs["scans"]]
    marker = tmp_path / "killed"
    with distributed.Client(cluster) as client:
        summary = run_tasks(KillOnce(job, marker), sources, outs, client=client, out_dir=tmp_path / "out")
    assert marker.exists()  # a worker did die
    assert summary.code == 0 and [o.written for o in summary.outcomes] == [True] * 6
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted([o.name for o in outs] + [".lock"])
    for out, source in zip(outs, sources):  # whole, and what one process writes
        single = tmp_path / f"single-{source.stem}.tif"
        if not single.exists():
            assert main(["-q", "reconstruct", str(source), "--out", str(single), "--registration", "optics"]) == 0
        assert out.read_bytes() == single.read_bytes()


def test_an_output_is_published_once(tmp_path):
    out = tmp_path / "x.tif"
    first, second = tmp_path / ".x.tif.1.tmp", tmp_path / ".x.tif.2.tmp"
    first.write_bytes(b"first")
    second.write_bytes(b"second")
    assert publish(first, out) and not publish(second, out)  # the second run of a task is discarded
    assert out.read_bytes() == b"first" and not first.exists() and not second.exists()
    outcome = run_task(lambda source, staging: Path(staging).write_bytes(b"again"), "x", out)
    assert outcome.skipped and out.read_bytes() == b"first"  # a done output is not run again


def test_a_lost_scheduler_exits_3_and_a_rerun_resumes(cluster, inputs, tmp_path, capsys):
    scans = [str(p) for p in inputs["scans"]]
    out = tmp_path / "out"
    out.mkdir()
    done = out / "scan1.classical.tif"  # what an earlier, interrupted run finished
    assert main(["-q", "reconstruct", scans[0], "--out", str(done), "--registration", "optics"]) == 0
    # A scheduler with no workers: the tasks wait on it until it is killed, a second after the
    # command has taken its output folder's lock (connected, submitting).
    proc = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                             "--port", "0", "--no-dashboard"], stderr=subprocess.PIPE, text=True)

    def kill_when_running():
        deadline = time.monotonic() + 60
        while not (out / ".lock").exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(1.0)
        proc.kill()

    try:
        address = None
        for line in proc.stderr:
            if "Scheduler at:" in line:
                address = line.split("Scheduler at:")[1].strip()
                break
        assert address
        threading.Thread(target=kill_when_running, daemon=True).start()
        started = time.monotonic()
        code = main(["-q", "reconstruct", *scans, "--out-dir", str(out), "--registration", "optics",
                     "--scheduler", address])
        err = capsys.readouterr().err
        assert code == 3 and "lost the Dask scheduler" in err and time.monotonic() - started < 30
        assert sorted(p.name for p in out.iterdir()) == [".lock", done.name]
    finally:
        proc.kill()
        proc.wait()
    code = main(["-q", "reconstruct", *scans, "--out-dir", str(out), "--registration", "optics", "--scheduler", cluster])
    assert code == 0 and "reconstructed 2 of 3 stacks" in capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == [".lock"] + [f"scan{k}.classical.tif" for k in (1, 2, 3)]


def test_learned_model_opened_once_per_worker(cluster, inputs, tmp_path, capsys):
    scans = [str(p) for p in inputs["scans"]]
    assert main(["-q", "reconstruct", *scans, "--method", "learned", "--registration", "optics",
                 "--out-dir", str(tmp_path), "--scheduler", cluster]) == 0

    def opened():
        from hbis_torch.reconstruct.learned.method import _runner

        info = _runner.cache_info()
        return info.misses, info.hits

    with distributed.Client(cluster) as client:
        counts = client.run(opened)
    assert sum(m + h for m, h in counts.values()) >= 3 and all(m <= 1 for m, _ in counts.values())


def test_pool_on_the_cluster_is_the_local_pool(cluster):
    from hbis_torch.cluster.pool import build_pool_on
    from hbis_torch.training.data import build_pool

    local = build_pool(2, 2, 16, 5)
    with distributed.Client(cluster) as client:
        remote = build_pool_on(client, build_pool, 2, 2, 16, 5)
    assert len(remote) == 2
    for a, b in zip(local, remote):
        assert a["scene"] == b["scene"]
        for key in ("base", "truth", "noise", "roi"):
            assert a[key].dtype == b[key].dtype and np.array_equal(a[key], b[key]), key


def test_simulate_many_on_the_cluster_matches_in_process_and_one_at_a_time(cluster, tmp_path, capsys, one_thread):
    """hbis simulate of many scenes and seeds: the same bytes on the cluster, in process, and as
    single commands; each stack's truth beside it; a rerun skips what is done."""
    import hashlib

    def digests(folder):
        return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.glob("*.tif"))}

    common = ["--h", "2", "--roi", "600,400,24,24", "--with-truth"]
    scenes = ["simulate", "--scene", "bars", "siemens-star", "--seed", "0", "3"]
    assert main(scenes + common + ["--out-dir", str(tmp_path / "here")]) == 0
    assert main(scenes + common + ["--out-dir", str(tmp_path / "there"), "--scheduler", cluster]) == 0
    here, there = digests(tmp_path / "here"), digests(tmp_path / "there")
    assert len(here) == 8 and here == there  # 4 stacks, 4 truths
    assert main(["simulate", "--scene", "siemens-star", "--seed", "3", "--h", "2", "--roi", "600,400,24,24",
                 "--out", str(tmp_path / "one.tif"), "--truth", str(tmp_path / "one.truth.tif")]) == 0
    assert np.array_equal(read_stack(tmp_path / "one.tif").frames,
                          read_stack(tmp_path / "here" / "siemens-star.seed3.tif").frames)
    capsys.readouterr()
    assert main(scenes + common + ["--out-dir", str(tmp_path / "here")]) == 0
    assert "4 done before, skipped" in capsys.readouterr().out and digests(tmp_path / "here") == here


@pytest.mark.parametrize("argv, message", [
    (["reconstruct", "a.tif", "--out", "x.tif", "--scheduler", "local:2"], "--scheduler needs --out-dir"),
    (["validate", "a.tif", "b.tif"], "--out-dir"),
    (["assemble", "a.avi", "--out-dir", "d", "--phases", "p.json"], "--out-dir is for bursts"),
    (["simulate", "--scene", "bars", "edges", "--h", "2", "--out", "x.tif"], "give --out-dir"),
    (["simulate", "--scene", "bars", "--h", "2", "--out", "x.tif", "--scheduler", "local:2"], "--scheduler needs --out-dir"),
    (["simulate", "--scene", "bars", "nope", "--h", "2", "--out-dir", "d"], "neither a built-in scene nor a file"),
    (["simulate", "--scene", "bars", "--h", "2", "--out", "x.tif", "--out-dir", "d"], "not both"),
])
def test_refused_before_any_work(argv, message, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_scheduler_spec():
    assert parse_scheduler("local:3").workers == 3 and parse_scheduler("local").workers >= 1
    assert parse_scheduler("host:8786").address == "tcp://host:8786"
    for bad in ("local:0", "local:x", ""):
        with pytest.raises(HbisInputError):
            parse_scheduler(bad)
    with pytest.raises(SystemExit) as exit_:  # argparse's one-line error
        main(["reconstruct", "a.tif", "--out-dir", "d", "--scheduler", "local:0"])
    assert exit_.value.code == 2

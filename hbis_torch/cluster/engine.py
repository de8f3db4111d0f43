"""The engine: many inputs, one task each, on a Dask scheduler or in this process.

A *job* is a picklable callable ``job(input, staging) -> list[str]`` that reads one input, writes
its whole output to the path ``staging`` and returns its messages (one line each). The engine
(:func:`run_tasks`) gives each input a task that

1. returns at once if the input's output exists already (a rerun resumes; nothing is overwritten),
   unless the run was asked to replace outputs (``overwrite``, the command's ``--overwrite``);
2. runs the job into a staging file beside the output, ``.NAME.<random>.tmp``;
3. publishes it with a hard link (``os.link``), which fails if the output exists, so that a
   task that ran twice (its worker was declared dead while it was still writing) publishes one
   whole file once and the second copy is discarded; where the file system has no hard links,
   ``os.rename`` (atomic, but the later copy then replaces the earlier, identical one); with
   ``overwrite``, ``os.replace``;
4. catches the input's failure: a bad input (:class:`~hbis_torch.errors.HbisInputError`) is
   exit code 2, anything else 1, named in one line; the other tasks go on.

Outputs are only ever whole: a worker killed mid-write leaves a ``.*.tmp`` file, never a
partial output, and the scheduler runs its task again on another worker (Dask's own retry of
the tasks of a lost worker). The client holds the output folder's lock
(:func:`hbis_torch.run_lock.lock_dir`) and removes what killed workers left before and after.

If the client loses the scheduler, every pending future is cancelled; :func:`run_tasks` raises
:class:`~hbis_torch.errors.HbisDeviceError` (exit code 3) and the outputs already published stay,
so the same command run again resumes.
"""

from __future__ import annotations

import errno
import os
import re
import sys
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

from hbis_torch.errors import HbisDeviceError, HbisInputError

LOCAL = re.compile(r"local(?::(\d+))?")


@dataclass(frozen=True)
class Scheduler:
    """Where the tasks run: ``local`` (a LocalCluster of ``workers`` processes) or ``address``."""

    address: str | None = None  # tcp://host:8786, a scheduler file's JSON is not taken here
    workers: int | None = None  # local:N

    @property
    def local(self) -> bool:
        return self.address is None

    def __str__(self) -> str:
        return f"local:{self.workers}" if self.local else str(self.address)


def parse_scheduler(text: str) -> Scheduler:
    """``local``, ``local:N`` (N worker processes, default: the CPUs this process may use) or a
    scheduler's address (``tcp://host:8786``, ``host:8786``).

    Raises
    ------
    HbisInputError
        An empty text, ``local:0`` or more than 1024 local workers.
    """
    text = str(text).strip()
    if not text:
        raise HbisInputError("--scheduler: give local, local:N or a scheduler's address (tcp://host:8786)")
    match = LOCAL.fullmatch(text)
    if match:
        n = int(match.group(1)) if match.group(1) else len(os.sched_getaffinity(0))
        if not 1 <= n <= 1024:
            raise HbisInputError(f"--scheduler {text}: N must be in 1..1024 worker processes")
        return Scheduler(workers=n)
    if text.startswith("local"):
        raise HbisInputError(f"--scheduler {text}: expected local or local:N with N a whole number")
    return Scheduler(address=text if "://" in text else f"tcp://{text}")


def import_distributed():
    """The ``distributed`` module, or one line saying how to install the ``[cluster]`` extra."""
    try:
        import distributed
    except ImportError:
        raise HbisInputError("--scheduler needs Dask: pip install 'hbis-torch[cluster]' "
                             "(or dask distributed)") from None
    return distributed


class Connection:
    """A Dask client on ``scheduler`` (a context manager; see :func:`connect`)."""

    def __init__(self, scheduler: Scheduler, timeout_s: float = 30.0):
        self.scheduler = scheduler
        self.timeout_s = timeout_s
        self.cluster = None
        self.client = None

    def __enter__(self):
        distributed = import_distributed()
        import logging

        if self.scheduler.local:
            import dask

            # ":0": the dashboard on a free port (8787 may be another cluster's). The workers'
            # statistical profiler (on by default: it samples the task's stack every 10 ms, taking
            # the interpreter lock from it) is off: a measurable share of the CPU time of small
            # tasks (docs/scale-out.md). The nannies hand this setting to the workers they start.
            with dask.config.set({"distributed.worker.profile.enabled": False}):
                self.cluster = distributed.LocalCluster(n_workers=self.scheduler.workers, threads_per_worker=1,
                                                        processes=True, dashboard_address=":0",
                                                        silence_logs=logging.ERROR)
            self.client = distributed.Client(self.cluster)
        else:
            try:
                self.client = distributed.Client(self.scheduler.address, timeout=f"{self.timeout_s}s")
            except (OSError, TimeoutError) as exc:
                raise HbisDeviceError(f"no Dask scheduler answers at {self.scheduler.address} ({exc}); "
                                      "start it (dask scheduler) or check the address, then retry") from None
        return self.client

    def __exit__(self, *exc):
        if self.client is not None and self.client.status != "running":
            quiet_dask_logs()  # the scheduler is gone: the client's reconnection attempts log tracebacks
        for thing in (self.client, self.cluster):
            if thing is not None:
                try:
                    thing.close()
                except Exception:  # noqa: BLE001 - closing a client whose scheduler is gone
                    pass
        return False


def quiet_dask_logs() -> None:
    """Silence Dask's loggers (each ``distributed.*`` logger has its own level): once the
    scheduler is lost, the client's background reconnection logs tracebacks that say nothing more
    than the one line this package prints."""
    import logging

    for name in ["distributed", *logging.root.manager.loggerDict]:
        if name.startswith("distributed"):
            logging.getLogger(name).setLevel(logging.CRITICAL + 1)


def connect(scheduler: Scheduler, timeout_s: float = 30.0) -> Connection:
    """A client on ``scheduler``: ``with connect(parse_scheduler("local:2")) as client: ...``.

    A local scheduler is a ``distributed.LocalCluster`` of worker processes with one thread each
    (each task runs on one core, as the in-process batch's stacks do); it is closed on exit.

    Raises
    ------
    HbisInputError
        Dask is not installed.
    HbisDeviceError
        No scheduler answers at the address within ``timeout_s``.
    """
    return Connection(scheduler, timeout_s)


def dashboard_link(client) -> str | None:
    """The scheduler's dashboard address, or None where it runs none (no ``bokeh`` there)."""
    import importlib.util

    if importlib.util.find_spec("bokeh") is None:  # the dashboard's pages need bokeh (on the client too)
        return None
    try:
        if "dashboard" not in client.scheduler_info().get("services", {}):
            return None
        return client.dashboard_link
    except Exception:  # noqa: BLE001 - only for a message
        return None


def worker_count(client) -> int:
    """The workers the scheduler has now (at least 1, for messages)."""
    try:
        return max(1, len(client.scheduler_info(n_workers=-1)["workers"]))
    except TypeError:  # older distributed: no n_workers keyword
        return max(1, len(client.scheduler_info()["workers"]))
    except Exception:  # noqa: BLE001 - only for the summary line
        return 1


def worker_plugin(threads: int, warm=None):
    """A ``distributed.WorkerPlugin`` (``client.register_plugin``): each worker process runs its
    tasks with ``threads`` torch threads, no progress bars and glibc's freed memory kept (as the
    ``hbis`` program does), then calls ``warm()`` once, e.g. to open a model, which the method's own
    cache (``hbis_torch.reconstruct.learned.method._runner``) keeps for every later task of that
    worker. The class is made here so that importing this module needs no Dask."""
    distributed = import_distributed()

    class _Setup(distributed.WorkerPlugin):
        name = "hbis-worker-setup"

        def __init__(self, threads, warm):
            self.threads, self.warm = threads, warm

        def setup(self, worker):
            prepare_worker(self.threads, self.warm)

    return _Setup(threads, warm)


def prepare_worker(threads: int, warm=None) -> None:
    """What :func:`worker_plugin` does in each worker process (also used in-process by tests).

    Every thread pool of the process gets ``threads`` threads: torch's (and MKL's with it) here,
    OpenCV's where it is installed (it would start one thread per core, and each worker of a
    machine would), OpenMP's and the BLAS libraries' through the environment Dask's nanny gives
    the worker (``OMP_NUM_THREADS=1`` and the like, ``distributed.nanny.pre-spawn-environ``)."""
    import importlib.util

    import torch

    from hbis_torch.progress import set_progress

    torch.set_num_threads(threads)
    if importlib.util.find_spec("cv2") is not None:
        import cv2

        cv2.setNumThreads(threads)
    set_progress(False)
    if warm is not None:
        try:
            warm()
        except Exception:  # noqa: BLE001 - a model that fails to open fails each task, with its message
            pass


# --------------------------------------------------------------------------- one task (worker side)


@dataclass
class Outcome:
    """What one task reports: ``code`` 0 (written, or found done), 2 (bad input), 1 (other error)."""

    code: int = 0
    messages: list = field(default_factory=list)
    written: bool = False  # this task published the output
    skipped: bool = False  # the output existed before the task ran
    seconds: float = 0.0
    worker: str = ""


def staging_path(out: Path) -> Path:
    """A fresh temporary name beside ``out``: ``.NAME.<32 hex>.tmp`` (what
    :func:`hbis_torch.run_lock.remove_temp_files` clears)."""
    return out.parent / f".{out.name}.{uuid.uuid4().hex}.tmp"


def output_of(staging) -> Path:
    """The output a staging file of :func:`staging_path` is for (``.NAME.<32 hex>.tmp`` -> ``NAME``):
    for a job that writes a file beside its output (a raw burst's preview)."""
    staging = Path(staging)
    match = re.fullmatch(r"\.(.+)\.[0-9a-f]{32}\.tmp", staging.name)
    if match is None:
        raise ValueError(f"{staging} is not a staging file of staging_path")
    return staging.parent / match.group(1)


def publish(staging: Path, out: Path, replace: bool = False) -> bool:
    """Move the whole file ``staging`` to ``out`` unless ``out`` exists; True if it was published.

    A hard link is atomic and refuses an existing ``out`` (two runs of one task publish once);
    without hard links (some network and FAT file systems) ``os.rename``. ``replace``: replace an
    existing ``out`` (``os.replace``, atomic)."""
    if replace:
        os.replace(staging, out)
        return True
    try:
        os.link(staging, out)
    except FileExistsError:
        return False
    except OSError as exc:
        if exc.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV, errno.EMLINK):
            raise
        if os.path.lexists(out):
            return False
        os.rename(staging, out)
        return True
    finally:
        if staging.exists() and os.path.lexists(out):
            staging.unlink(missing_ok=True)
    return True


def run_task(job, source, out, overwrite: bool = False) -> Outcome:
    """Run ``job`` on ``source`` into ``out`` (the task a worker runs; see the module's docstring);
    ``overwrite``: replace ``out`` where it exists, instead of skipping the task."""
    started = time.perf_counter()
    out = Path(out)
    outcome = Outcome(worker=f"{os.uname().nodename}:{os.getpid()}")
    if os.path.lexists(out) and not overwrite:
        outcome.skipped = True
        return outcome
    staging = staging_path(out)
    try:
        outcome.messages = list(job(source, staging) or [])
        outcome.written = publish(staging, out, replace=overwrite)
    except HbisInputError as exc:
        outcome.code, outcome.messages = 2, outcome.messages + [str(exc)]
    except Exception as exc:  # noqa: BLE001 - one input's failure must not stop the others
        outcome.code, outcome.messages = 1, outcome.messages + [f"{type(exc).__name__}: {exc}"]
    finally:
        staging.unlink(missing_ok=True)
    outcome.seconds = time.perf_counter() - started
    return outcome


# --------------------------------------------------------------------------- many tasks (client side)


@dataclass
class Summary:
    """The run's outcome per input, in input order, and its wall time in seconds."""

    sources: list
    outputs: list
    outcomes: list
    seconds: float
    where: str

    @property
    def code(self) -> int:
        """The command's exit code: the worst input's (0, 1 or 2)."""
        return max([o.code for o in self.outcomes], default=0)

    @property
    def failed(self) -> list:
        return [(s, o) for s, o in zip(self.sources, self.outcomes) if o.code]

    def lines(self, verb: str, noun: str, out_dir) -> list[str]:
        """The summary printed at the end: counts, then ``  exit CODE: INPUT`` per failure."""
        done = sum(o.written for o in self.outcomes)
        skipped = sum(o.skipped or (not o.written and not o.code) for o in self.outcomes)
        head = (f"{verb} {done} of {len(self.sources)} {noun} into {out_dir} in {self.seconds:.1f} s ({self.where})"
                + (f"; {skipped} done before, skipped" if skipped else ""))
        return [head] + [f"  exit {o.code}: {s}" for s, o in self.failed]


def run_tasks(job, sources, outputs, *, client=None, desc: str = "tasks", prefix: str = "hbis",
              out_dir=None, overwrite: bool = False, jobs: int | None = None) -> Summary:
    """Run ``job`` on every source into its output: on ``client``'s cluster, or in this process
    on threads when ``client`` is None.

    Parameters
    ----------
    job : callable
        ``job(source, staging) -> list[str]`` (the module's docstring); picklable for a cluster.
    sources, outputs : list of Path
        One output per source, distinct; outputs that exist are skipped.
    client : distributed.Client or None
        Where to run; None: in this process, ``jobs`` tasks at once, each on one torch thread.
    desc : str
        The progress bar's label.
    prefix : str
        Messages are printed on stderr as ``PREFIX: SOURCE: MESSAGE``, as each task ends.
    out_dir : Path or None
        Locked for the run (a second run on it is refused) and cleared of leftover ``.*.tmp`` files.
    overwrite : bool
        Replace outputs that exist (the command's ``--overwrite``) instead of skipping their inputs.
    jobs : int or None
        Without ``client``: tasks at once on threads of this process (default: the CPUs it may
        use, at most the number of inputs); each task has one torch thread whatever ``jobs`` is.

    Returns
    -------
    Summary

    Raises
    ------
    HbisDeviceError
        The scheduler was lost (exit 3); the outputs published so far stay.
    """
    from hbis_torch.progress import progress
    from hbis_torch.run_lock import lock_dir, remove_temp_files

    lock = lock_dir(out_dir) if out_dir is not None else None
    try:
        if out_dir is not None:
            remove_temp_files(out_dir)
        started = time.monotonic()
        outcomes: list = [None] * len(sources)

        def report(i: int, outcome: Outcome) -> None:
            outcomes[i] = outcome
            for line in outcome.messages:
                print(f"{prefix}: {sources[i]}: {line}", file=sys.stderr)

        # Outputs done before are skipped here, without a task (each task checks again).
        todo = [i for i, out in enumerate(outputs) if overwrite or not os.path.lexists(out)]
        for i in sorted(set(range(len(sources))) - set(todo)):
            outcomes[i] = Outcome(skipped=True)
        some = ([sources[i] for i in todo], [outputs[i] for i in todo], lambda k, outcome: report(todo[k], outcome),
                overwrite)
        jobs = jobs or min(len(os.sched_getaffinity(0)), max(1, len(sources)))
        with progress(total=len(sources), desc=desc, unit="task") as bar:
            bar.update(len(sources) - len(todo))
            if client is None:
                _run_here(job, *some, bar, jobs)
                where = f"in this process, {jobs} at once, one thread each"
            else:
                if todo:
                    _run_on(client, job, *some, bar)
                where = f"{worker_count(client)} Dask workers"
        if out_dir is not None:
            remove_temp_files(out_dir)  # what killed workers left
        return Summary(list(sources), list(outputs), outcomes, time.monotonic() - started, where)
    finally:
        if lock is not None:
            lock.close()


def _run_here(job, sources, outputs, report, overwrite, bar, jobs: int = 1) -> None:
    """Run the tasks in this process, ``jobs`` side by side on threads (torch and its libraries
    release the interpreter lock in their kernels), each on one torch thread as on a worker: the
    same sums in the same order, the same bits (tested, for bursts too: the last-bit differences
    once seen between two bursts assembled at once were :data:`hbis_torch.capture.brightness.LSTSQ_DRIVER`'s
    cause)."""
    from concurrent.futures import ThreadPoolExecutor

    import torch

    from hbis_torch.progress import progress_enabled, set_progress

    before, inner = torch.get_num_threads(), progress_enabled()
    torch.set_num_threads(1)
    set_progress(False)  # no bars inside: tasks run side by side
    try:
        with ThreadPoolExecutor(max_workers=max(1, min(jobs, len(sources)))) as pool:
            futures = [pool.submit(run_task, job, source, out, overwrite) for source, out in zip(sources, outputs)]
            for i, future in enumerate(futures):
                report(i, future.result())
                bar.update()
    finally:
        set_progress(None if inner else False)
        torch.set_num_threads(before)


def _run_on(client, job, sources, outputs, report, overwrite, bar) -> None:
    """Submit one task per source and report each as the scheduler says it is finished."""
    distributed = import_distributed()

    token = uuid.uuid4().hex[:8]
    # The job travels with each task (a few kB: the options): scattered data would be lost with
    # the last worker holding it, a task's own arguments never are.
    futures = [client.submit(run_task, job, str(source), str(out), overwrite, pure=False,
                             key=f"hbis-{token}-{i}-{Path(out).name}")
               for i, (source, out) in enumerate(zip(sources, outputs))]
    index = {future.key: i for i, future in enumerate(futures)}
    lost = 0
    for future in distributed.as_completed(futures):
        i = index[future.key]
        if future.status == "finished":
            report(i, future.result())
        elif future.status == "cancelled" or client.status != "running":
            lost += 1  # cancelled by the client when it lost the scheduler
            continue
        else:  # only the engine raises in a task: a worker killed too often (KilledWorker)
            exc = future.exception()
            report(i, Outcome(code=1, messages=[f"{type(exc).__name__}: {exc}"]))
        bar.update()
    if lost or client.status != "running":
        quiet_dask_logs()
        raise HbisDeviceError(f"lost the Dask scheduler with {lost} of {len(futures)} tasks unfinished; the outputs "
                              "written are kept: run the same command again (on a live scheduler) to do the rest")

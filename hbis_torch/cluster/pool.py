"""A training pool simulated on a Dask cluster: one task per example, the same pool.

Every example of a pool has its own seed, :func:`hbis_torch.training.data.example_seed` (pool
seed, index), so example i is the same whichever process simulates it; here each example is one
task (``builder(h, count, size, seed, [i])``) and the results come back in index order, equal bit
for bit to ``builder(h, count, size, seed, indices)`` in one process (tested). ``training/train_sr.py``
takes it with ``pool_scheduler=ADDRESS`` (not ``local:N``: its spawned workers would run the
script, which has no main guard, again).
"""

from __future__ import annotations

import uuid


def build_pool_on(scheduler, builder, h: int, count: int, size: int, seed: int, indices=None) -> list[dict]:
    """``builder``'s examples of ``indices``, simulated on ``scheduler``.

    Parameters
    ----------
    scheduler : str or distributed.Client
        ``local[:N]``, a scheduler's address, or a connected client (left open).
    builder : callable
        :func:`hbis_torch.training.data.build_pool` or
        :func:`hbis_torch.training.burst_data.build_burst_pool` (importable on the workers).
    h, count, size, seed : int
        As for ``builder``: the scale, the pool's size, the ROI side in sensor pixels, the pool's seed.
    indices : iterable of int, optional
        The examples to simulate (default: all ``count``).

    Returns
    -------
    list of dict
        The examples, in the order of ``indices``.

    Raises
    ------
    HbisDeviceError
        The scheduler was lost or cannot be reached (exit code 3).
    """
    from hbis_torch.cluster.engine import connect, import_distributed, parse_scheduler, worker_plugin
    from hbis_torch.errors import HbisDeviceError
    from hbis_torch.progress import progress

    indices = list(range(count) if indices is None else indices)
    if not indices:
        return []
    distributed = import_distributed()
    if isinstance(scheduler, distributed.Client):
        client, connection = scheduler, None
    else:
        connection = connect(parse_scheduler(scheduler))
        client = connection.__enter__()
    try:
        client.register_plugin(worker_plugin(1))  # one torch thread per worker process
        token = uuid.uuid4().hex[:8]
        futures = [client.submit(builder, h, count, size, seed, [i], pure=False, key=f"pool-{token}-{i}")
                   for i in indices]
        with progress(total=len(futures), desc="simulate pool", unit="example") as bar:
            for _ in distributed.as_completed(futures):
                bar.update()
        if any(f.status == "cancelled" for f in futures) or client.status != "running":
            from hbis_torch.cluster.engine import quiet_dask_logs

            quiet_dask_logs()
            raise HbisDeviceError("lost the Dask scheduler while simulating the pool; run again on a live scheduler")
        return [part[0] for part in client.gather(futures)]
    finally:
        if connection is not None:
            connection.__exit__(None, None, None)

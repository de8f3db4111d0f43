"""Scale-out on Dask (``distributed``, the optional ``[cluster]`` extra): many inputs, one task
each, on a scheduler (a ``LocalCluster``, SSH, SLURM through dask-jobqueue, Kubernetes), with
whole outputs published once, resumable reruns and the failures named (docs/scale-out.md).

* :mod:`hbis_torch.cluster.engine`: scheduler connection, one task per input, atomic
  publication, the run's summary; needs Dask only when a scheduler is used.
* :mod:`hbis_torch.cli.jobs`: what ``hbis reconstruct``, ``hbis assemble --burst`` and
  ``hbis validate`` do to one input.
* :mod:`hbis_torch.cli.many`: ``--scheduler`` and the commands' many-input paths.
* :mod:`hbis_torch.cluster.pool`: a training pool simulated on the cluster, example for example
  the pool the local run builds.
"""

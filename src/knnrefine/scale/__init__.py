"""Scale-out, in one place: runs and checks over several processes, on a Dask cluster, and
meshes kept as folders of parts.

One vocabulary throughout: ``workers`` are processes that run at the same time (local ones,
or a Dask cluster's), and the points are cut into ``strips``, one per worker and round, so
that no process holds them all; a mesh written in ``parts`` is a folder with one file per
part, which ``PartitionedMesh`` reads part by part.

- ``tiled``: the plan of a tiled run (strips from a sample, rounds, the seam checks) and
  ``LocalStore``, the points held by local worker processes;
- ``distributed``: the same on a Dask cluster (``refine``, ``certify``, ``density``);
- ``parts``: ``PartitionedMesh`` and ``write_partitioned``, and d_{P,k} part by part.

The kernels that keep a tile's run inside its region are the engine's (``engine.region``).
"""

from .parts import PartitionedMesh, write_partitioned

__all__ = ["PartitionedMesh", "write_partitioned"]

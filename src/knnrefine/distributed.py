"""kNNRefine with its tiles on a Dask cluster (``pip install "knnrefine[dask]"``).

``refine`` runs the tiled refinement of ``api.refine(..., workers=N)`` with every round's
tiles as Dask tasks (``Client.get_executor``): a tile is a pure function of its inputs, so a
task lost with its worker is run again (``retries``, and Dask's rescheduling of the tasks of
a dead worker) and nothing is half-applied; the rounds, the final pass and the mesh are
assembled in the calling process. The result is an ordinary ``Mesh``, certified like any.

Where it stands: the points are read into the calling process (a Dask array or DataFrame is
computed, a Parquet dataset read), because the final pass counts with an index of all of
them; tiles receive only their strip's points. Partitioned output and per-tile certification
are not built yet.
"""

import contextlib
import os

import numpy as np

from .api import refine as _refine
from .errors import InputError
from .validation import as_points

DEFAULT_COLUMNS = ("x", "y")


def _dask():
    try:
        import dask  # noqa: F401
        import distributed  # noqa: F401
    except ImportError:
        raise ImportError(
            'knnrefine.distributed needs Dask: pip install "knnrefine[dask]"'
        ) from None


def read_source(source, columns=DEFAULT_COLUMNS, weights=None):
    """(points (n, 2), weights or None) from a NumPy array, a Dask array, a pandas or Dask
    DataFrame (``columns`` hold x and y, ``weights`` may name a column), or the path of a
    Parquet dataset (read with Dask, only ``columns`` and the weight column)."""
    if isinstance(source, (str, os.PathLike)):
        _dask()
        import dask.dataframe as dd

        if not os.path.exists(source):
            raise InputError(f"no Parquet dataset at {os.fspath(source)!r}")
        wanted = list(columns) + ([weights] if isinstance(weights, str) else [])
        try:
            source = dd.read_parquet(source, columns=wanted)
        except Exception as exc:  # a missing column, not Parquet at all
            raise InputError(f"could not read {wanted} from the Parquet dataset: {exc}") from None
    if hasattr(source, "columns"):  # pandas or Dask DataFrame
        missing = [c for c in columns if c not in source.columns]
        if missing:
            raise InputError(
                f"the DataFrame has no column {missing[0]!r} (columns {list(source.columns)}): "
                "name the coordinates with columns=(x, y)"
            )
        if isinstance(weights, str):
            if weights not in source.columns:
                raise InputError(f"the DataFrame has no weight column {weights!r}")
            frame = source[list(columns) + [weights]]
            frame = frame.compute() if hasattr(frame, "compute") else frame
            return as_points(frame[list(columns)].to_numpy()), frame[weights].to_numpy()
        source = source[list(columns)]
    if isinstance(weights, str):
        raise InputError("a weight column name needs a DataFrame or Parquet source")
    if hasattr(source, "compute"):  # Dask array or DataFrame
        source = source.compute()
    if hasattr(source, "to_numpy"):
        source = source.to_numpy()
    return as_points(source), weights


def refine(
    source, k, tau=3.0, *, client=None, workers=None, columns=DEFAULT_COLUMNS, weights=None,
    retries=2, **options,
):  # fmt: skip
    """kNNRefine of ``source`` with its tiles as tasks of a Dask cluster; the same result
    type and guarantees as ``knnrefine.refine`` (``options``: its keyword arguments,
    periodic, box, min_size, max_vertices, time_limit, progress).

    source : NumPy array (n, 2), Dask array, pandas or Dask DataFrame, or a Parquet path
        See ``read_source`` (``columns``, ``weights``: a weight array, or a column's name).
    client : dask.distributed.Client, optional
        Where the tiles run; None: a LocalCluster of ``workers`` processes (default: this
        machine's cores, at least 2) with one thread each, closed afterwards.
    workers : int, optional
        Tiles per round (default: the client's worker threads, at least 2).
    retries : int
        How often Dask runs a failed tile again.
    """
    _dask()
    from distributed import Client

    if workers is not None and (
        isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 2
    ):
        raise InputError(f"workers must be an integer >= 2 (tiles per round), got {workers!r}")
    if client is not None and not hasattr(client, "get_executor"):
        raise InputError(f"client must be a dask.distributed.Client, got {client!r}")
    points, w = read_source(source, columns, weights)
    with contextlib.ExitStack() as stack:
        if client is None:
            cluster = local_cluster(workers or max(2, os.cpu_count() or 1))
            client = stack.enter_context(Client(stack.enter_context(cluster)))
        tiles = workers or max(2, sum(client.nthreads().values()))
        executor = client.get_executor(pure=False, retries=int(retries))
        return _refine(points, k, tau, weights=w, workers=tiles, executor=executor, **options)


def local_cluster(workers):
    """A Dask LocalCluster for tiles: ``workers`` processes of one thread, each engine on
    one thread (KNNREFINE_THREADS=1), the dashboard on any free port."""
    _dask()
    from distributed import LocalCluster

    return LocalCluster(
        n_workers=int(workers), threads_per_worker=1, processes=True, dashboard_address=":0",
        env={"KNNREFINE_THREADS": "1"},
    )  # fmt: skip

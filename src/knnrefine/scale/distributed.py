"""kNNRefine on a Dask cluster (``pip install "knnrefine[dask]"``): the points stay on the
workers, partition by partition.

``refine`` runs the tiled refinement of ``api.refine(..., workers=N)`` with ``DaskStore``
holding the points: the source's partitions are read and checked on the workers; only a
sample (the plan: initial mesh, strips, coarse pass) comes to the calling process. Each
strip's points are cut from the partitions once, where they lie, and its counting index is
built once on the worker that runs that strip's tiles, and kept there for every round.
Rounds send a tile only the vertices in its strip. A tile is a pure function of its inputs,
so one lost with its worker runs again (``retries``, and Dask's rescheduling; a lost strip
index is rebuilt from its partitions), and nothing is half-applied. The points come to the
calling process only when the rounds leave elements that no strip settled (``stats["rounds"]``
says so: ``fetched_points``), as where elements of a non-periodic box straddle the data's
edge wider than the strips overlap.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from .. import _pipeline as pipeline
from .. import _validation as V
from .._options import RunOptions
from .._sampling import canonical, key_sample
from ..errors import InputError
from .parts import check_output, write_partitioned
from .tiled import continue_store, in_region, refine_store, run_tile, split_strips, tile_index

if TYPE_CHECKING:  # the annotations' types only
    from ..certify.certificate import Certificate
    from ..density.estimate import KnnDensity
    from ..mesh import Mesh
    from .parts import PartitionedMesh

DEFAULT_COLUMNS = ("x", "y")


def _dask():
    try:
        import dask  # noqa: F401
        import distributed  # noqa: F401
    except ImportError:
        raise ImportError(
            'knnrefine.scale.distributed needs Dask: pip install "knnrefine[dask]"'
        ) from None


def partitions(
    source: Any,
    columns: Sequence[str] = DEFAULT_COLUMNS,
    weights: Any = None,
    chunk: int = 1_000_000,
) -> list:
    """The source as Dask partitions; nothing is computed here.

    Parameters
    ----------
    source : NumPy array (n, 2) or (n, 3), Dask array, pandas or Dask DataFrame, or a Parquet
        path. A NumPy array is cut into ``chunk`` rows; a Parquet dataset is read with Dask,
        only the columns needed.
    columns : two or three str
        The x and y (and z: points in space) columns of a DataFrame or Parquet dataset.
    weights : array-like, str or None
        An array, or a column's name.
    chunk : int
        Rows per partition of a NumPy array.

    Returns
    -------
    list of (Dask delayed partition, its weights)
        The partition an (n_i, d) array or a pandas DataFrame, its weights an array slice,
        a column's name, or None.
    """
    _dask()
    import dask
    import dask.array as da
    import dask.dataframe as dd

    if isinstance(source, (str, os.PathLike)):
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
        wanted = list(columns)
        if isinstance(weights, str):
            if weights not in source.columns:
                raise InputError(f"the DataFrame has no weight column {weights!r}")
            wanted.append(weights)
        elif weights is not None:
            raise InputError("with a DataFrame source, weights names one of its columns")
        frame = source[wanted]
        if not isinstance(frame, dd.DataFrame):
            frame = dd.from_pandas(frame, chunksize=chunk, sort=False)
        return [(part, weights) for part in frame.to_delayed()]
    if isinstance(weights, str):
        raise InputError("a weight column name needs a DataFrame or Parquet source")
    if isinstance(source, da.Array):
        if source.ndim != 2 or source.shape[1] not in (2, 3):
            raise InputError(
                f"points must have shape (n, 2) in the plane or (n, 3) in space, got {source.shape}"
            )
        parts = list(source.rechunk({1: source.shape[1]}).to_delayed().ravel())
        rows = source.chunks[0]
        if weights is not None and any(np.isnan(r) for r in rows):
            raise InputError(
                "weights need a Dask array with known chunk sizes (compute_chunk_sizes)"
            )
    else:
        arr = V.as_points(source, source_dim(source, columns))
        parts = [dask.delayed(arr[a : a + chunk]) for a in range(0, len(arr), chunk)]
        rows = [min(chunk, len(arr) - a) for a in range(0, len(arr), chunk)]
    if weights is None:
        return [(part, None) for part in parts]
    weights = V.check_weights(weights, int(sum(rows)))
    ends = np.cumsum(rows).astype(int)
    return [(p, weights[e - r : e]) for p, r, e in zip(parts, rows, ends, strict=True)]


def source_dim(source, columns):
    """The points' dimension: the columns named for a DataFrame or Parquet dataset, the
    array's columns otherwise (2 unless three are given)."""
    if isinstance(source, (str, os.PathLike)) or hasattr(source, "columns"):
        return len(columns)
    shape = np.shape(source) if not hasattr(source, "shape") else source.shape
    return 3 if len(shape) == 2 and shape[1] == 3 else 2


def _arrays(part, columns, weights, dim):
    """(xy float64 (n, dim), weights (n,) or None) of one partition, checked."""
    if hasattr(part, "columns"):
        w = part[weights].to_numpy(np.float64) if isinstance(weights, str) else None
        part = part[list(columns)].to_numpy()
    else:
        w = weights
    if len(part) == 0:
        return np.zeros((0, dim)), None if w is None else np.zeros(0)
    xy = V.as_points(part, dim)
    if w is not None:
        w = np.ascontiguousarray(w, np.float64)
        if not (np.isfinite(w).all() and (w >= 0).all()):
            raise InputError("weights must be finite and >= 0 (drop such points or weigh them 0)")
    return xy, w


def _stats(part):
    xy, w = part
    if len(xy) == 0:
        return 0, None, None, 0.0
    lo = [float(xy[:, a].min()) for a in range(xy.shape[1])]
    hi = [float(xy[:, a].max()) for a in range(xy.shape[1])]
    return len(xy), lo, hi, 0.0 if w is None else float(w.sum())


def _box_domain(source, columns):
    """The domain of the source's points: the plane or space (no sphere on a cluster)."""
    return "space" if source_dim(source, columns) == 3 else "plane"


def _digests(part, first, n0):
    """The digests (``_engine/digest.py``) of one partition's rows, the first being row
    ``first`` of all: (points before row n0, points from it on, the same of the weights)."""
    from .._engine.digest import digest_of

    xy, w = part
    cut = min(max(n0 - first, 0), len(xy))
    d = xy.shape[1]
    out = [digest_of(xy[:cut], first * d), digest_of(xy[cut:], (first + cut) * d)]
    if w is not None:
        out += [digest_of(w[:cut], first), digest_of(w[cut:], first + cut)]
    return out


def _rows_from(part, first, n0):
    xy, w = part
    cut = min(max(n0 - first, 0), len(xy))
    return xy[cut:], None if w is None else w[cut:]


def _near(part, frame, period, region):
    """One partition's points in ``region`` of the torus of ``period`` (``frame``: the map
    into it), in its coordinates, and their weights."""
    xy, w = part
    internal = frame(xy)
    inside = in_region(internal, region, 0.0, period)
    return internal[inside], None if w is None else w[inside]


def _inside(part, box, per):
    if len(part[0]):
        V.check_inside(part[0], box, per, warn=False)


def _sample(part, fraction):
    """One partition's keyed sample (``_sampling.key_sample``), merged in ``canonical`` order."""
    xy, w = part
    return key_sample(xy, fraction, w)


def _cut(part, frame, period, sets, pad):
    """One partition's points in the coordinates ``frame(points)`` (a torus of ``period``),
    cut into the strips of each set of regions widened by ``pad``."""
    xy, w = part
    internal = frame(xy)
    out = []
    for regions in sets:
        rows, bounds = split_strips(internal, regions, pad, period)
        mine = [rows[bounds[j] : bounds[j + 1]] for j in range(len(regions))]
        out.append([(internal[r], None if w is None else w[r]) for r in mine])
    return out


def _piece(cut, s, j):
    return cut[s][j]


def _join(pieces):
    xy = np.concatenate([p[0] for p in pieces])
    return xy, None if pieces[0][1] is None else np.concatenate([p[1] for p in pieces])


def _strip_index(*pieces):
    return tile_index(*_join(pieces))


def _strip_call(fn, payload, *pieces):
    return fn(*_join(pieces), payload)


class DaskStore:
    """The points of a tiled run on a Dask cluster (``scale/tiled.py`` says what a store
    does): partitions and strip indexes live on the workers; strip j of either set is
    built on, and its tiles sent to, worker j mod W (another if that one is gone)."""

    def __init__(self, client, parts, columns=DEFAULT_COLUMNS, retries=2, dim=2):
        import dask

        self.client, self.retries, self.dim = client, int(retries), dim
        arrays = [dask.delayed(_arrays)(p, columns, w, dim) for p, w in parts]
        self.parts = client.compute(arrays, retries=self.retries)
        stats = client.gather(client.map(_stats, self.parts, pure=False))
        self.counts = [int(s[0]) for s in stats]
        self.n = int(sum(self.counts))
        if self.n == 0:
            raise InputError("points is empty: give at least one point")
        weighted = any(w is not None for _, w in parts)
        self.weight = float(sum(s[3] for s in stats)) if weighted else None
        full = [s for s in stats if s[0]]
        lo = [min(s[1][a] for s in full) for a in range(dim)]
        self.bounds = (lo, [max(s[2][a] for s in full) for a in range(dim)])
        self.index = None
        self.workers = sorted(client.scheduler_info()["workers"])

    def check_inside(self, box, per):
        self.client.gather(self.client.map(_inside, self.parts, box=box, per=per, pure=False))

    def sample(self, fraction):
        got = self.client.gather(self.client.map(_sample, self.parts, fraction=fraction))
        xy = np.concatenate([g[0] for g in got])
        w = None if self.weight is None else np.concatenate([g[1] for g in got])
        return canonical(xy, w, np.concatenate([g[2] for g in got]))

    def prepare(self, emb, sets, pad):
        """Cut every partition into strips where it lies; build each strip's index once."""
        c = self.client
        frame, period = emb.to_internal, emb.period_internal
        cuts = [c.submit(_cut, p, frame, period, sets, pad, pure=False) for p in self.parts]
        self.index = []
        for s, regions in enumerate(sets):
            row = []
            for j in range(len(regions)):
                pieces = [c.submit(_piece, cut, s, j, pure=False) for cut in cuts]
                row.append(c.submit(_strip_index, *pieces, pure=False, **self._on(j)))
            self.index.append(row)

    def _on(self, j):
        """Where strip j's tasks go: worker j mod W of those listed (read again when none
        were: a worker restarting as the store was made), anywhere when none is listed."""
        if not self.workers:
            self.workers = sorted(self.client.scheduler_info()["workers"])
        if not self.workers:  # the scheduler places it when a worker comes
            return {"retries": self.retries}
        return {
            "workers": [self.workers[j % len(self.workers)]],
            "allow_other_workers": True,
            "retries": self.retries,
        }

    def run_round(self, s, tasks):
        c = self.client
        futures = [
            c.submit(run_tile, task, index, pure=False, **self._on(j))
            for j, (task, index) in enumerate(zip(tasks, self.index[s], strict=True))
        ]
        return c.gather(futures)

    def map_strips(self, fn, frame, regions, pad, payloads):
        """fn(points, weights, payload) for each strip of ``regions`` widened by ``pad``, on
        the workers: each partition cut where it lies (``LocalStore.map_strips``)."""
        c = self.client
        cuts = [
            c.submit(_cut, p, frame, frame.period, [regions], pad, pure=False) for p in self.parts
        ]
        futures = []
        for j, payload in enumerate(payloads):
            pieces = [c.submit(_piece, cut, 0, j, pure=False) for cut in cuts]
            futures.append(c.submit(_strip_call, fn, payload, *pieces, pure=False, **self._on(j)))
        return c.gather(futures)

    def points(self):
        got = self.client.gather(self.parts)
        xy = np.concatenate([g[0] for g in got])
        return xy, None if self.weight is None else np.concatenate([g[1] for g in got])

    def _firsts(self):
        return np.concatenate([[0], np.cumsum(self.counts)[:-1]]).astype(int).tolist()

    def digests(self, n0):
        """The points' digests (``_engine/digest.py``), summed over the partitions where
        they lie: (points before row n0, from it on; the same of the weights, or None)."""
        got = self.client.gather(self.client.map(_digests, self.parts, self._firsts(),
                                                 [n0] * len(self.parts), pure=False))  # fmt: skip
        sums = [sum(g[i] for g in got) % (1 << 64) for i in range(len(got[0]))]
        return sums[:2], (sums[2:] if self.weight is not None else None)

    def rows_from(self, n0):
        """(points, weights or None) of the rows from row n0 on, fetched."""
        got = self.client.gather(self.client.map(_rows_from, self.parts, self._firsts(),
                                                 [n0] * len(self.parts), pure=False))  # fmt: skip
        xy = np.concatenate([g[0] for g in got])
        return xy, None if self.weight is None else np.concatenate([g[1] for g in got])

    def points_in(self, emb, region):
        """(points in internal coordinates, weights or None) of every point in ``region``
        of ``emb``'s torus (corner, widths), fetched."""
        got = self.client.gather(self.client.map(
            _near, self.parts, frame=emb.to_internal, period=np.array(emb.period_internal),
            region=np.asarray(region, float), pure=False))  # fmt: skip
        xy = np.concatenate([g[0] for g in got]) if got else np.zeros((0, self.dim))
        return xy, None if self.weight is None else np.concatenate([g[1] for g in got])

    def close(self):
        for f in self.parts + [i for row in self.index or [] for i in row]:
            f.release()
        self.parts, self.index = [], None


def refine(
    source: Any,
    k: float | None = None,
    tau: float | None = None,
    *,
    client: Any = None,
    workers: int | None = None,
    columns: Sequence[str] = DEFAULT_COLUMNS,
    weights: Any = None,
    retries: int = 2,
    periodic: bool | tuple = False,
    box: tuple | None = None,
    min_size: float | None = None,
    max_vertices: int | None = None,
    time_limit: float | None = None,
    progress: Callable | None = None,
    output: str | os.PathLike | None = None,
    parts: int | None = None,
    force: bool = False,
    start: Mesh | PartitionedMesh | None = None,
) -> Mesh | PartitionedMesh:
    """kNNRefine of ``source`` on a Dask cluster, the points never gathered in this process
    (module docstring); the same result type and guarantees as ``knnrefine.refine``.

    Parameters
    ----------
    source : NumPy array (n, 2) or (n, 3), Dask array, pandas or Dask DataFrame, or a
        Parquet path. See ``partitions`` (``columns``: three for points in space;
        ``weights``: an array, or a column's name).
    k, tau, periodic, box, min_size, max_vertices, time_limit, progress
        As for ``knnrefine.refine`` (tau: 3 by default).
    client : dask.distributed.Client, optional
        Where the strips run; None: a LocalCluster of ``workers`` processes (default: this
        machine's cores, at least 2) with one thread each, closed afterwards.
    workers : int, optional
        Workers, one strip each per round (default: the client's worker threads, at least 2).
    retries : int
        How often Dask runs a failed task again.
    output : path, optional
        Write the mesh as a folder of ``parts`` parts (default: one per worker) and return it
        as a ``PartitionedMesh`` (``write_partitioned``: written atomically, a finished marker
        last; ``force`` overwrites an existing folder), in the plane and in space.
    start : Mesh or PartitionedMesh, optional
        Continue this mesh (``knnrefine.refine``'s ``start``): the source's first rows are
        its points, verified by their digest where they lie (``Stats.points_digest``, summed
        over the partitions); the new rows are fetched, and the old points only where the
        run may move (``tiled.continue_store``): the region about the new points, widened
        while it leaves anything unsettled, then all of them.

    Returns
    -------
    Mesh or PartitionedMesh

    Raises
    ------
    InputError
        Bad options or points, checked before any work.
    """
    if output is not None:
        check_output(output, parts, force)
    asked = {"k": k, "tau": tau, "periodic": periodic, "box": box, "min_size": min_size}
    if start is not None:
        start = start.to_mesh() if hasattr(start, "to_mesh") else start
        asked = pipeline.start_options(start, _box_domain(source, columns), asked)
    asked["tau"] = 3.0 if asked["tau"] is None else asked["tau"]
    with _store(source, client, workers, columns, weights, retries) as (store, tiles):
        opt = RunOptions.check(
            store.n, store.weight, lambda: V.default_box(np.array(store.bounds)),
            store.check_inside, **asked, max_vertices=max_vertices, time_limit=time_limit,
            progress=progress, dim=store.dim,
        )  # fmt: skip
        lo, hi = store.bounds
        V.fold_warning(lo, hi, opt.box, opt.periodic, stacklevel=3)
        if start is None:
            (h, _), hw = store.digests(store.n)  # summed where the points lie
            mesh = refine_store(store, opt, tiles)
            mesh.stats.points_digest = pipeline.digest_of_hashes(
                (h, None if hw is None else hw[0]))  # fmt: skip
        else:

            def hashes(n0):
                (h_old, h_new), hw = store.digests(n0)
                return (h_old, None if hw is None else hw[0]), (
                    h_new, None if hw is None else hw[1])  # fmt: skip

            digest = pipeline.continued_digest(start, store.n, store.weight is not None, hashes)
            new_pts, new_w = store.rows_from(int(start.stats.n))
            pipeline.check_in_start_box(start, new_pts)
            mesh = continue_store(store, start, opt.continuing(start, digest), new_pts, new_w)
            mesh.stats.points_digest = digest
    if output is None:
        return mesh
    return write_partitioned(mesh, output, parts or tiles, force)


def certify(
    mesh: Mesh,
    source: Any,
    *,
    client: Any = None,
    workers: int | None = None,
    columns: Sequence[str] = DEFAULT_COLUMNS,
    weights: Any = None,
    retries: int = 2,
    samples: int = 100_000,
    n_random: int = 20_000,
    max_point_probes: int = 100_000,
    random_state: int | np.random.Generator | None = 0,
) -> Certificate:
    """``knnrefine.certify`` of a mesh against the points of ``source`` on a Dask cluster,
    the points never gathered here: every count and d_{P,k} is asked strip by strip on the
    workers where the strips' points are (``scale.checks.certify_store``); the mesh's own checks
    (its triangulation, in exact arithmetic where floating point is not conclusive) run in
    this process.

    Parameters
    ----------
    mesh : Mesh
    source, client, workers, columns, weights, retries
        As for ``refine``.
    samples, n_random, max_point_probes, random_state
        As for ``knnrefine.certify``.

    Returns
    -------
    Certificate
    """
    from .checks import certify_store

    with _store(source, client, workers, columns, weights, retries) as (store, tiles):
        store.check_inside(mesh.box, mesh.periodic)
        return certify_store(mesh, store, tiles, samples=samples, n_random=n_random,
                             max_point_probes=max_point_probes,
                             random_state=random_state)  # fmt: skip


def density(
    pmesh: PartitionedMesh | str | os.PathLike,
    source: Any,
    *,
    client: Any = None,
    workers: int | None = None,
    columns: Sequence[str] = DEFAULT_COLUMNS,
    weights: Any = None,
    retries: int = 2,
    normalized: bool = True,
    subdivide: bool = True,
) -> KnnDensity:
    """The kNN density estimate of a partitioned mesh, answered part by part
    (``scale.parts.PartitionedDistance``): exact d_{P,k} at every part's nodes is asked strip
    by strip on the workers where the points of ``source`` are, never gathered here.

    Parameters
    ----------
    pmesh : PartitionedMesh or path
        From ``refine(..., output=)``.
    source, client, workers, columns, weights, retries
        As for ``refine``.
    normalized, subdivide
        As for ``KnnDensity``.

    Returns
    -------
    KnnDensity
        Evaluate, ``grid``, ``mass``, ``sample``.

    Raises
    ------
    InputError
        Not a partitioned mesh, or points that are not the run's.
    """
    from ..density import KnnDensity
    from .parts import PartitionedDistance, PartitionedMesh

    if isinstance(pmesh, (str, os.PathLike)):
        pmesh = PartitionedMesh(pmesh)
    if not isinstance(pmesh, PartitionedMesh):
        raise InputError(
            f"density needs a PartitionedMesh (refine(..., output=)), got {type(pmesh).__name__};"
            " for a Mesh in memory use knnrefine.KnnDensity(mesh, points)"
        )
    with _store(source, client, workers, columns, weights, retries) as (store, tiles):
        store.check_inside(pmesh.box, pmesh.periodic)
        distance = PartitionedDistance.of_store(pmesh, store, tiles, subdivide)
    return KnnDensity.of_distance(distance, normalized=normalized)


@contextlib.contextmanager
def _store(source, client, workers, columns, weights, retries):
    """(DaskStore of the source's partitions, strips per round) on ``client`` (a LocalCluster
    of ``workers`` processes when None, closed afterwards); options checked first."""
    _dask()
    from distributed import Client

    if workers is not None and (
        isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 2
    ):
        raise InputError(f"workers must be an integer >= 2 (tiles per round), got {workers!r}")
    if client is not None and not hasattr(client, "get_executor"):
        raise InputError(f"client must be a dask.distributed.Client, got {client!r}")
    parts = partitions(source, columns, weights)
    with contextlib.ExitStack() as stack:
        if client is None:
            cluster = local_cluster(workers or max(2, os.cpu_count() or 1))
            client = stack.enter_context(Client(stack.enter_context(cluster)))
        tiles = int(workers or max(2, sum(client.nthreads().values())))
        store = DaskStore(client, parts, columns, retries, source_dim(source, columns))
        stack.callback(store.close)
        yield store, tiles


def local_cluster(workers):
    """A Dask LocalCluster for tiles: ``workers`` processes of one thread, each engine on
    one thread (KNNREFINE_THREADS=1), the dashboard on any free port. Its processes are
    forked where the platform can (as ``refine(..., workers=N)``'s): Dask's default, spawn,
    imports the caller's script again in every worker, so a script without the ``if
    __name__ == "__main__":`` guard started clusters in its workers, and a script read from
    standard input (``python -``, ``python -c``) could not start one at all. Elsewhere
    (macOS, Windows) the guard is needed, as for any multiprocessing."""
    _dask()
    import multiprocessing

    import dask
    from distributed import LocalCluster

    method = "fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn"
    worker_log = logging.getLogger("distributed.worker")
    quiet = QuietShutdownHeartbeat()
    worker_log.addFilter(quiet)  # forked workers keep it; this process drops it below
    try:
        with dask.config.set({"distributed.worker.multiprocessing-method": method}):
            return LocalCluster(
                n_workers=int(workers), threads_per_worker=1, processes=True,
                dashboard_address=":0", env={"KNNREFINE_THREADS": "1"},
            )  # fmt: skip
    finally:
        worker_log.removeFilter(quiet)


class QuietShutdownHeartbeat(logging.Filter):
    """Drops distributed's "Failed to communicate with scheduler during heartbeat" record (an
    error with its traceback) in the worker processes of ``local_cluster``. Their scheduler
    runs in the calling process and closes with the run, and a heartbeat caught in flight by
    that close (a race in distributed, known upstream) printed a traceback after a run that
    had succeeded. A worker of such a cluster cannot lose its scheduler otherwise."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith("Failed to communicate with scheduler")

"""The options of one run, checked once before any work: ``RunOptions``; and what every
domain's run shares around them: the user's progress callback (``Progress``), the vertex
budget from the size estimate (``vertex_budget``) and the k = 1 notice (``warn_k1``).

A run in the plane or in space, in one process, in tiles or on a Dask cluster, reads its
options from one frozen object made by ``RunOptions.check``: each option validated in one
place, the box defaulted and the points checked against it, the deadline set from the clock
the run's budget errors read (``past``), and what cannot fit refused up front (the initial
mesh of the torus the box makes must fit the vertex budget and memory).
"""

import copy
import dataclasses
import inspect
import math
import numbers
import sys
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from . import _validation as V
from ._engine import size
from ._engine.embedding import Embedding
from ._engine.geometry import RESOLUTION_ANGLE
from ._engine.initial import GRIDS, GRIDS3, grid_shape, grid_shape3
from .errors import BudgetError, FloorWarning, InputError, LargeRunWarning

DEFAULT_MIN_SIZE = 1e-6  # resolution floor, relative to the box's longer side
DEFAULT_MIN_ANGLE = 1e-6 * math.pi  # the sphere's floor: a millionth of half a great circle
INITIAL_BYTES3 = 2500  # peak memory per initial vertex while an M0 is built in space (2.3 KB)


@dataclass(frozen=True)
class RunOptions:
    """What one run was asked, checked: k (a count, or a weight for weighted points), tau,
    the periodic axes and the box (its default the points' bounding box), the resolution
    floor ``min_size`` (input units), the vertex budget (None: chosen from the size
    estimate), the time limit and its ``deadline`` (a ``time.perf_counter()`` value from
    ``t_start``), and the progress callback."""

    k: int | float
    tau: float
    periodic: tuple[bool, ...]
    box: tuple[float, ...]
    min_size: float
    max_vertices: int | None
    time_limit: float | None
    progress: Callable | None
    t_start: float
    deadline: float | None
    start: Any = None  # the mesh a continued run starts from (``pipeline.checked``)
    points_digest: str = ""  # the points' digest, known from their check
    given: Any = None  # a continued run's points, all of them, as given (float64)
    given_weights: Any = None  # and their weights (float64), or None

    def continuing(self, start, digest: str, given=None, given_weights=None) -> "RunOptions":
        """These options with the points' digest ``digest`` (``pipeline.points_digest``)
        known; for a run continued from the mesh ``start``, with all its points and weights
        as given (the run's checked ones are the new rows alone)."""
        return dataclasses.replace(self, start=start, points_digest=digest, given=given,
                                   given_weights=given_weights)  # fmt: skip

    @property
    def dim(self) -> int:
        return len(self.periodic)

    @property
    def domain(self) -> str:
        """The domain the run is in: "plane" or "space" (``knnrefine._domains``)."""
        return "plane" if self.dim == 2 else "space"

    @property
    def bytes_per_vertex(self) -> int:
        """A run's peak memory per mesh vertex (``engine.size``), for its budget."""
        return size.BYTES_PER_VERTEX if self.dim == 2 else size.BYTES_PER_VERTEX3

    def start_budget(self, n: int) -> int:
        """The vertex budget the initial mesh must fit: the user's, else max(10^6, 2 n) in
        the plane and max(10^6, 4 n) in space."""
        if self.max_vertices is not None:
            return int(self.max_vertices)
        return max(10**6, (2 if self.dim == 2 else 4) * n)

    def past(self, what: str) -> None:
        """BudgetError if the time limit has passed (checked between steps of the setup)."""
        now = time.perf_counter()
        if self.deadline is not None and now > self.deadline:
            raise BudgetError(
                f"time_limit reached while {what}, before refinement began; raise time_limit",
                progress={"vertices": 0, "moves": {}, "seconds": now - self.t_start},
            )

    @classmethod
    def check(
        cls,
        n: int,
        total: float | None,
        bounds: Callable[[], tuple],
        check_inside: Callable[[tuple, tuple], None],
        *,
        k,
        tau=3.0,
        periodic=False,
        box=None,
        min_size=None,
        max_vertices=None,
        time_limit=None,
        progress=None,
        dim: int = 2,
    ) -> "RunOptions":
        """The options of a run on n points (weights summing to ``total``, or None) in
        ``dim`` dimensions, each checked once, before any work.

        Parameters
        ----------
        n, total : the number of points and their total weight (None: unweighted)
        bounds : callable returning the points' default box (its bounding box)
        check_inside : callable(box, periodic) refusing points outside an explicit box
        k, tau, periodic, box, min_size, max_vertices, time_limit, progress
            As ``knnrefine.refine``.
        dim : 2 or 3

        Returns
        -------
        RunOptions

        Raises
        ------
        InputError
            An option out of range, a periodic run without a box, points outside an explicit
            box, an initial mesh that cannot fit the budget or memory.
        """
        t_start = time.perf_counter()
        time_limit, deadline = check_time_limit(time_limit, t_start)
        k, tau = check_k_tau(k, tau, n, total)
        per = V.check_periodic(periodic, dim)
        if box is None:
            if any(per):
                corners = "xmin, ymin, xmax, ymax" if dim == 2 else "x0, y0, z0, x1, y1, z1"
                degrees = ", ".join(["-180"] * dim + ["180"] * dim)
                raise InputError(
                    f"a periodic run needs box=({corners}): the periods are its sides (for "
                    f"angles in degrees, e.g. box=({degrees}))"
                )
            box = bounds()
        else:
            box = V.check_box(box, dim)
            check_inside(box, per)
        side = max(box[dim + a] - box[a] for a in range(dim))
        min_size = DEFAULT_MIN_SIZE * side if min_size is None else check_min_size(min_size)
        max_vertices = V.check_max_vertices(max_vertices)
        check_progress(progress)
        V.check_resolution(box, per)
        options = cls(k, tau, tuple(per), tuple(box), float(min_size), max_vertices,
                      time_limit, progress, t_start, deadline)  # fmt: skip
        check_initial_budget(options.box, options.periodic, options.start_budget(n))
        return options


def check_box_run(points, weights, dim, *, radius=None, before=None, **asked):
    """A run in a box (the plane's or space's ``run.checked``): its points (n, dim), weights
    and options checked before any work. ``before``: (count, total weight) of the rows a
    continued run verified already (by digest: ``pipeline.checked``); ``points`` and
    ``weights`` are then the new rows alone.

    Returns
    -------
    pts : ndarray (n, dim), w : ndarray (n,) or None, options : RunOptions
    """
    if radius is not None:
        raise InputError("radius is the sphere's: give it with sphere=True")
    pts, w, n, total = _new_rows(points, weights, before, lambda x: V.as_points(x, dim), dim)

    def inside(b, p):
        if len(pts):  # (a continued run without new points has none to check)
            V.check_inside(pts, b, p)

    return pts, w, RunOptions.check(n, total, lambda: V.default_box(pts), inside, **asked,
                                    dim=dim)  # fmt: skip


def _new_rows(points, weights, before, as_points, dim):
    """(points, weights, n, total weight) of a run's checked rows: all of them, or with
    ``before`` = (n0, total0) of rows a continued run verified by their digest, only the
    new ones (possibly none), n and the total counting both."""
    if before is None:
        pts = as_points(points)
        w = None if weights is None else V.check_weights(weights, len(pts))
        return pts, w, len(pts), None if w is None else math.fsum(w)
    n0, total0 = before
    pts = as_points(points) if len(points) else np.zeros((0, dim))
    w = None
    if weights is not None:
        w = V.check_weights(weights, len(pts), positive=False)
    total = None if w is None else float(total0) + math.fsum(w)
    return pts, w, n0 + len(pts), total


def check_sphere_run(points, weights, *, periodic=False, box=None, before=None, **asked):
    """A run on the sphere (its ``run.checked``): its points as unit vectors (n, 3), weights
    and options checked before any work; the options it has no use for refused. ``before``:
    as ``check_box_run``'s.

    Returns
    -------
    xyz : ndarray (n, 3), w : ndarray (n,) or None, options : SphereOptions
    """
    if periodic is not False or box is not None:
        raise InputError(
            "the sphere has no box and no periodic axes: drop box= and periodic= with "
            "sphere=True (longitudes wrap by themselves)"
        )
    xyz, w, n, total = _new_rows(points, weights, before, V.as_sphere_points, 3)
    return xyz, w, SphereOptions(n, total, **asked)


class SphereOptions:
    """What a run on the sphere was asked, checked before any work: ``RunOptions``' options
    but the box and the periodic axes, with a radius; lengths are the radius' units, the
    floor an angle (``floor_angle``)."""

    domain = "sphere"
    dim = 3  # unit vectors
    start = None  # the mesh a continued run starts from (``pipeline.checked``)
    points_digest = ""  # the points' digest, known from their check
    given = None  # a continued run's points, all of them, as given (float64)
    given_weights = None  # and their weights (float64), or None
    bytes_per_vertex = size.BYTES_PER_VERTEX_SPHERE  # a run's peak memory per vertex

    def __init__(self, n, total, *, k, tau=3.0, radius=None, min_size=None,
                 max_vertices=None, time_limit=None, progress=None):  # fmt: skip
        self.t_start = time.perf_counter()
        self.radius = V.check_radius(radius)
        self.k, self.tau = check_k_tau(k, tau, n, total)
        if min_size is None:
            self.min_angle = DEFAULT_MIN_ANGLE
        else:
            self.min_angle = check_min_size(min_size) / self.radius
        self.max_vertices = V.check_max_vertices(max_vertices)
        self.time_limit, self.deadline = check_time_limit(time_limit, self.t_start)
        self.progress = check_progress(progress)

    def continuing(self, start, digest: str, given=None, given_weights=None) -> "SphereOptions":
        """``RunOptions.continuing``."""
        out = copy.copy(self)
        out.start, out.points_digest = start, digest
        out.given, out.given_weights = given, given_weights
        return out

    @property
    def floor_angle(self) -> float:
        """The Break floor in effect: ``min_size`` as an angle, at least the engine's
        resolution (``refine_sphere.RESOLUTION_ANGLE``), below which nothing is split."""
        return max(self.min_angle, RESOLUTION_ANGLE)

    @property
    def min_size(self) -> float:
        return self.floor_angle * self.radius


def check_time_limit(time_limit, t_start):
    """(time_limit as a float or None, its deadline on ``time.perf_counter``'s clock)."""
    if time_limit is None:
        return None, None
    if (
        isinstance(time_limit, bool)
        or not isinstance(time_limit, numbers.Real)
        or not (np.isfinite(float(time_limit)) and float(time_limit) > 0)
    ):
        raise InputError(f"time_limit must be a positive number of seconds, got {time_limit!r}")
    return float(time_limit), t_start + float(time_limit)


def check_k_tau(k, tau, n, total):
    """k (default sqrt(n) / 2 of the points or their total weight) and tau, checked."""
    if k is None:
        k = V.default_k(n if total is None else total)
    k = V.check_k(k, n) if total is None else V.check_weighted_k(k, total)
    return k, V.check_tau(tau)


def check_min_size(min_size):
    """A resolution floor given by the user: a finite number >= 0."""
    if isinstance(min_size, bool) or not np.isfinite(min_size) or min_size < 0:
        raise InputError(f"min_size must be a finite number >= 0, got {min_size!r}")
    return float(min_size)


def check_initial_budget(box, per, budget):
    """The smallest initial mesh of the default torus must fit the vertex budget (and, in
    space, where building it costs INITIAL_BYTES3 a vertex, half the memory): a thin or
    elongated periodic box needs a fine grid across its long sides (1 x 1 x 0.002 needs
    1,500 x 1,500 x 3 vertices). InputError otherwise, before any work."""
    period = Embedding.make(box, per).period_internal
    if len(per) == 2:
        shapes = [np.array(grid_shape(*period, g[0])) for g in GRIDS]
        memory, per_vertex = np.inf, 0
    else:
        shapes = [grid_shape3(period, g[0]) for g in GRIDS3]
        memory, per_vertex = size.memory_bytes(), INITIAL_BYTES3
    shape = min(shapes, key=lambda s: int(np.prod(s)))
    need = int(np.prod(shape))
    if need <= budget and need * per_vertex <= memory / 2:
        return
    dims = " x ".join(f"{int(v):,}" for v in shape)
    if max(shape) <= 4 * min(shape):
        raise InputError(
            f"max_vertices={budget:,} is too small: the initial mesh alone has {dims} = "
            f"{need:,} vertices; raise max_vertices"
        )
    torus = "torus" if len(per) == 2 else "3-torus"
    cost = "" if len(per) == 2 else f", about {need * per_vertex / 1e9:.2g} GB to build"
    raise InputError(
        f"the box {tuple(box)} is too elongated or thin for its periodic axes: the initial "
        f"mesh of the {torus} alone needs {dims} = {need:,} vertices{cost} (max_vertices="
        f"{budget:,}); rescale the coordinates, use a less elongated periodic box (or make "
        "its short axis non-periodic), or raise max_vertices"
    )


LARGE_RUN_BYTES = 2e9  # runs expected to need more memory than this say so up front


def check_progress(progress):
    """``progress`` as every call takes it: None (silent), True (a progress bar) or a
    callable; else InputError, before any work."""
    if progress is None or isinstance(progress, (bool, np.bool_)) or callable(progress):
        return progress
    raise InputError(
        "progress must be True (a progress bar) or a callable(vertices, pending[, phase]), "
        f"got {progress!r}"
    )


class ProgressBar:
    """``progress=True``: a tqdm bar of the vertices so far (``tqdm.auto``: a widget in
    notebooks, text in a terminal), shown only after a second, gone when the mesh is done;
    the phases (compiling, assembling, an application's stage) as its description."""

    def __init__(self, desc="refining", unit=" vertices"):
        self.desc, self.unit, self.bar = desc, unit, None

    def __call__(self, count, pending, phase="refining"):
        if self.bar is None:
            from tqdm.auto import tqdm

            self.bar = tqdm(total=None, unit=self.unit, delay=1.0, desc=self.desc, leave=False,
                            dynamic_ncols=True)  # fmt: skip
        bar = self.bar
        if phase == "refining":
            bar.set_postfix_str(f"{pending} queued", refresh=False)
        else:
            bar.set_description_str(phase, refresh=False)
            bar.set_postfix_str("", refresh=False)
        bar.update(max(count - bar.n, 0))  # honours the delay: short runs show no bar
        if phase == "done":
            self.close()

    def close(self):
        """Take the bar away (a run that stopped early never says "done")."""
        if self.bar is not None:
            self.bar.close()


class Progress:
    """The user's progress callback: progress(vertices, pending) while refining; if it takes
    a ``phase`` argument, also phase="compiling" before a first compilation,
    phase="assembling" / "done" while the mesh is assembled, and progress(count, 0, phase)
    for an application's work after it (``stage``: the density estimator's "choosing the
    smoothing", pairs scored). ``True`` is a bar (``ProgressBar``), False and None nothing."""

    def __init__(self, callback):
        callback = check_progress(callback)
        if callback is True:
            callback = ProgressBar()
        elif callback is False:
            callback = None
        self.callback = callback
        self.phases = False
        if callback is not None:
            try:
                params = inspect.signature(callback).parameters.values()
                self.phases = any(
                    p.name == "phase" or p.kind is inspect.Parameter.VAR_KEYWORD for p in params
                )
            except (TypeError, ValueError):
                pass

    def compiling(self):
        if self.phases:
            self.callback(0, 0, phase="compiling")

    def refining(self, vertices, pending):
        if self.callback is not None:
            self.callback(vertices, pending)

    def stage(self, count, phase):
        """Work after the refinement (an application's): count done so far in ``phase``,
        reported to callbacks that take a phase."""
        if self.phases:
            self.callback(count, 0, phase=phase)

    def assembling(self, vertices, done=False):
        if self.callback is None:
            return
        if self.phases:
            self.callback(vertices, 0, phase="done" if done else "assembling")
        else:
            self.callback(vertices, 0)


def vertex_budget(estimated, opt, m0, n):
    """The vertex budget: the user's max_vertices, else ten times the estimate (at least
    10^6), but no more than the machine's memory holds. The estimate is within 5% on uniform
    points but off by up to 8x on clustered data (benchmarks/mesh_size.py), so only a run
    whose estimate exceeds twice the memory (by default) or eight times the user's budget is
    refused before any work; one expected to need more than 2 GB says so (LargeRunWarning)."""
    check_size(estimated, opt, n)
    if opt.max_vertices is not None:
        return int(opt.max_vertices)
    fits = int(0.9 * size.memory_bytes() / opt.bytes_per_vertex)
    return int(max(10**6, 2 * m0, min(10 * estimated, fits)))


def check_size(estimated, opt, n):
    """What every domain says of a run's expected size (``estimated`` vertices) before any
    work: the k = 1 notice (``warn_k1``); a refusal (BudgetError) of a run far beyond the
    user's max_vertices (8 times) or, without one, beyond twice the machine's memory; a
    LargeRunWarning for one expected to need more than 2 GB. ``opt``: the run's options
    (k, max_vertices, min_size, bytes_per_vertex)."""
    k, max_vertices, min_size = opt.k, opt.max_vertices, opt.min_size
    need = estimated * opt.bytes_per_vertex
    memory = size.memory_bytes()
    warn_k1(k, estimated, n, min_size)
    hint = (
        "k = 1 refines every input point down to min_size: use k >= 2 or a larger min_size"
        if k == 1
        else "use a larger k or a larger min_size"
    )
    if max_vertices is not None and estimated > 8 * max_vertices:
        raise BudgetError(
            f"this run needs about {estimated:.3g} vertices, far beyond "
            f"max_vertices={max_vertices}; {hint}, or raise max_vertices",
            progress={"vertices": 0, "moves": {}, "seconds": 0.0},
        )
    if max_vertices is None and need > 2 * memory:
        raise BudgetError(
            f"this run needs about {estimated:.3g} vertices, about {need / 1e9:.3g} GB, far "
            f"more than this machine's {memory / 1e9:.3g} GB; {hint}, or pass max_vertices "
            "to insist",
            progress={"vertices": 0, "moves": {}, "seconds": 0.0},
        )
    if need > LARGE_RUN_BYTES:
        warnings.warn(
            f"this run will need about {estimated:.3g} vertices and {need / 1e9:.2g} GB of memory "
            f"(n = {n}, k = {k}, min_size = {min_size:.3g})",
            LargeRunWarning,
            stacklevel=user_stacklevel(),
        )


def user_stacklevel():
    """The ``stacklevel`` that shows a warning at the user's line: the first frame outside
    knnrefine, counted from the caller of ``warnings.warn``."""
    frame, level = sys._getframe(2), 2
    while frame is not None and frame.f_globals.get("__name__", "").startswith("knnrefine"):
        frame, level = frame.f_back, level + 1
    return level


def warn_floor(under, n, k, min_size, default):
    """The one FloorWarning rule of every domain, after the run: when more than half of the
    ``n`` input points lie in elements left at the floor still holding k points (``under``
    of them), the bounds are not claimed for most of the data. k = 1 was said before the run
    (``warn_k1``). ``default``: how the domain's default min_size is set, for the advice.
    Shown at the caller's line."""
    if not under > n / 2 or k == 1:
        return
    warnings.warn(
        f"{under} of the {n} points ({100 * under / n:.0f}%) lie in circumballs or cells "
        f"smaller than min_size = {min_size:.3g} that still hold k = {k} points: the bounds "
        f"are not claimed there (Mesh.floor_points says where); min_size defaults to "
        f"{default}: pass a smaller min_size",
        FloorWarning,
        stacklevel=user_stacklevel(),
    )


def warn_k1(k, estimated, n, min_size):
    """Up front, a FloorWarning that k = 1 refines around every input point down to the
    floor (d_{P,1} vanishes on P), with the vertices expected (``estimated``, of ``n``
    points): several per point, thousands in space. Shown at the caller's line."""
    if k != 1:
        return
    warnings.warn(
        f"k = 1 refines around every input point down to min_size = {min_size:.3g} (d_P1 is 0 "
        f"at each point): about {estimated:,.0f} vertices are expected, {estimated / n:,.0f} "
        "per point; the bounds are not claimed below the floor. Use k >= 2 or a larger "
        "min_size",
        FloorWarning,
        stacklevel=user_stacklevel(),
    )

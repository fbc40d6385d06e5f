"""Python side of the engine: owns the flat arrays, takes the initial mesh, runs the kernels.

Everything here is O(1) Python per kernel call; the work happens in the ``kernel``s.
Coordinates are internal: the torus is [0, lx) x [0, ly) with lx, ly <= 1 multiples of the
grid step q (``geometry``).
"""

import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import EngineError
from . import refine as R
from .geometry import FLOOR_BITS, Q
from .index import STACK_SIZE
from .initial import initial_grid
from .queue import Q_SIZE, Q_USED, new_queue
from .triangulation import C_NT, C_NV, MAX_CAVITY, P_LX, P_LY, set_all_circumcircles

MAX_DEGREE = 4096  # scratch for a vertex's neighbours; a well-spaced mesh has degree < 20


@dataclass
class RunResult:
    """What a refinement produced, in internal coordinates."""

    vxy: np.ndarray  # (m, 2) vertices
    kind: np.ndarray  # (m,) int8, refine.INITIAL ... refine.CLEAN
    tv: np.ndarray  # (2m, 3) triangle corners
    tn: np.ndarray  # (2m, 3) neighbours
    to: np.ndarray  # (2m, 3, 2) corner offsets
    tcc: np.ndarray  # (2m, 2) circumcenters (triangle frame)
    tr2: np.ndarray  # (2m,) squared circumradii
    tstate: np.ndarray  # (2m,) circumball states
    vcell: np.ndarray  # (m,) cell states
    vflag: np.ndarray  # (m,) flags (Clean floor)
    counters: dict = field(default_factory=dict)
    status: str = "done"


def _grow(a, n):
    out = np.zeros((n,) + a.shape[1:], a.dtype)
    out[: a.shape[0]] = a
    return out


class Refinement:
    """The state of one kNNRefine run: triangulation, queues, scratch and counters."""

    def __init__(self, index, k, lx, ly, tau, min_size, max_vertices, m0=None, grid=Q):
        """index: the counting kd-tree over P in internal coordinates (``build_index``); m0:
        the initial mesh (vxy, tv, to, tn) on the grid step ``grid``, by default
        ``initial.initial_grid(lx, ly)``. Elements smaller than 2^14 grid (the resolution
        floor) or than min_size are never split."""
        self.lx = lx
        self.ly = ly
        self.index = index
        self.n = int(index[0].shape[0])
        vxy, tv, to, tn = initial_grid(lx, ly, q=grid)[:4] if m0 is None else m0
        self.grid = grid
        clean_floor = grid * 2.0**FLOOR_BITS
        m0 = vxy.shape[0]
        cap_v = max(1024, 4 * m0)
        cap_t = 2 * cap_v
        self.vxy = _grow(vxy, cap_v)
        self.vtri = np.zeros(cap_v, np.int32)
        self.vtri[tv[:, 0]] = np.arange(tv.shape[0], dtype=np.int32)
        self.vtri[tv[:, 1]] = np.arange(tv.shape[0], dtype=np.int32)
        self.vkind = np.zeros(cap_v, np.int8)
        self.vcell = np.zeros(cap_v, np.int8)
        self.vflag = np.zeros(cap_v, np.int8)
        self.tv = _grow(tv, cap_t)
        self.tn = _grow(tn, cap_t)
        self.to = _grow(to, cap_t)
        self.tcc = np.zeros((cap_t, 2))
        self.tr2 = np.zeros(cap_t)
        self.tstamp = np.zeros(cap_t, np.int32)
        self.tstate = np.zeros(cap_t, np.int8)
        self.tmark = np.zeros(cap_t, np.int32)
        self.vslot_a = np.zeros(cap_v, np.int32)
        self.vslot_b = np.zeros(cap_v, np.int32)
        self.queues = [new_queue(cap_t), new_queue(cap_v), new_queue(cap_v)]
        self.cav = np.zeros(MAX_CAVITY + 2, np.int32)
        self.cav_s = np.zeros((MAX_CAVITY + 2, 2), np.int64)
        self.bnd = np.zeros((MAX_CAVITY + 2, 4), np.int32)
        self.bnd_o = np.zeros((MAX_CAVITY + 2, 4), np.int64)
        self.work = (
            np.zeros(MAX_DEGREE),
            np.zeros(MAX_DEGREE),
            np.zeros(MAX_DEGREE),
            np.zeros(STACK_SIZE, np.int64),
        )
        self.cnt = np.zeros(R.N_COUNTERS, np.int64)
        self.cnt[C_NV] = m0
        self.cnt[C_NT] = tv.shape[0]
        self.cnt[R.C_K] = k
        self.cnt[R.C_MAX_VERTICES] = max_vertices
        self.prm = np.zeros(R.N_PARAMS)
        self.prm[P_LX] = lx
        self.prm[P_LY] = ly
        self.prm[R.P_TAU2] = tau * tau * (1.0 - 1e-12)
        self.floor = max(float(min_size), clean_floor)  # the Break floor in internal units
        self.prm[R.P_FLOOR2] = self.floor * self.floor
        self.prm[R.P_CLEAN_FLOOR2] = clean_floor * clean_floor
        self.prm[R.P_GRID] = grid
        self.prm[R.P_INFLATE] = 1.0 + 1e-9
        tri = self._tri()
        ver = self._ver()
        set_all_circumcircles(tri, ver, self.prm, tv.shape[0])
        R.queue_all(tri, ver, tuple(self.queues), self.work, self.cnt, self.prm)

    # -- tuples handed to the kernels (rebuilt after growth) --
    def _tri(self):
        return (self.tv, self.tn, self.to, self.tcc, self.tr2, self.tstamp, self.tstate)

    def _ver(self):
        return (self.vxy, self.vtri, self.vkind, self.vcell, self.vflag)

    def _scr(self):
        return (self.tmark, self.vslot_a, self.vslot_b, self.cav, self.cav_s, self.bnd, self.bnd_o)

    def _grow_if_needed(self):
        """Double every array that could overflow during the next insertion."""
        nv, nt = self.cnt[C_NV], self.cnt[C_NT]
        cap_v = self.vxy.shape[0]
        if nv + 1 > cap_v:
            n = 2 * cap_v
            for name in ("vxy", "vtri", "vkind", "vcell", "vflag", "vslot_a", "vslot_b"):
                setattr(self, name, _grow(getattr(self, name), n))
        cap_t = self.tv.shape[0]
        if nt + 2 > cap_t:
            n = 2 * cap_t
            for name in ("tv", "tn", "to", "tcc", "tr2", "tstamp", "tstate", "tmark"):
                setattr(self, name, _grow(getattr(self, name), n))
        for i, base in enumerate((R.C_Q_TRI, R.C_Q_CELL, R.C_Q_CLEAN)):
            head, ent_id, ent_aux, ent_next = self.queues[i]
            if self.cnt[base + Q_USED] + R.HEADROOM > ent_id.shape[0]:
                n = 2 * ent_id.shape[0]
                self.queues[i] = (head, _grow(ent_id, n), _grow(ent_aux, n), _grow(ent_next, n))

    def run(self, deadline=None, progress=None, interrupts=None):
        """Refine to completion, in kernel calls of about 50 ms. Returns a STATUS_* code:
        DONE, MAX_VERTICES, or STEPS when ``deadline`` (a time.perf_counter() value) passed.
        After every call: progress(vertices, queued), then ``interrupts.check()`` (Ctrl-C),
        then the deadline; the next call is sized not to overshoot it."""
        t0 = time.perf_counter()
        steps = 2000
        rate = None  # insertions per second, measured
        while True:
            before = int(self.cnt[C_NV])
            t1 = time.perf_counter()
            status = R.refine_steps(
                self._tri(),
                self._ver(),
                tuple(self.queues),
                self._scr(),
                self.work,
                self.cnt,
                self.prm,
                self.index,
                steps,
            )
            now = time.perf_counter()
            done = int(self.cnt[C_NV]) - before
            if done > 0:  # calls cut short (GROW) measure the rate too, never inflate it
                rate = done / max(now - t1, 1e-6)
                steps = int(min(max(rate * 0.05, 100), 200000))
            if progress is not None:
                progress(int(self.cnt[C_NV]), self.pending())
            if interrupts is not None:
                interrupts.check()
            if status == R.STATUS_ERROR:
                raise EngineError(f"refinement kernel failed with code {self.cnt[R.C_ERROR]}")
            if status in (R.STATUS_DONE, R.STATUS_MAX_VERTICES):
                self.time_refine = time.perf_counter() - t0
                return status
            if status == R.STATUS_GROW:
                self._grow_if_needed()
            if deadline is not None:
                now = time.perf_counter()
                if now >= deadline:
                    self.time_refine = now - t0
                    return R.STATUS_STEPS
                if rate is not None:
                    steps = max(1, min(steps, int(rate * (deadline - now)) + 1))

    def pending(self):
        """Queued candidates (an upper bound on the work left, not a promise)."""
        return int(sum(self.cnt[b + Q_SIZE] for b in (R.C_Q_TRI, R.C_Q_CELL, R.C_Q_CLEAN)))

    @property
    def vertices(self):
        return int(self.cnt[C_NV])

    def counters(self):
        """Moves of each kind (from the vertices' kinds) and the counting tests so far."""
        nv = self.vertices
        kinds = np.bincount(self.vkind[:nv], minlength=len(R.KIND_NAMES))
        return {
            "moves": {name: int(kinds[i]) for i, name in enumerate(R.KIND_NAMES)},
            "disk_tests": int(self.cnt[R.C_DISK_TESTS]),
            "cell_tests": int(self.cnt[R.C_CELL_TESTS]),
            "failed_insertions": int(self.cnt[R.C_FAILED]),
        }

    def result(self):
        nv, nt = self.vertices, int(self.cnt[C_NT])
        counters = self.counters()
        return RunResult(
            vxy=self.vxy[:nv].copy(),
            kind=self.vkind[:nv].copy(),
            tv=self.tv[:nt].copy(),
            tn=self.tn[:nt].copy(),
            to=self.to[:nt].copy(),
            tcc=self.tcc[:nt].copy(),
            tr2=self.tr2[:nt].copy(),
            tstate=self.tstate[:nt].copy(),
            vcell=self.vcell[:nv].copy(),
            vflag=self.vflag[:nv].copy(),
            counters=counters,
        )

"""How many vertices a run will need, before it starts: the default budget and the warnings.

For points that look locally like a Poisson process of any intensity rho(x), pi rho d_{P,k}^2
is Gamma(k, 1)-distributed, so the integral of 1 / d_{P,k}^2 over the box (the size the paper's
open problem 3 asks about) is about pi n / (k - 1) whatever the density. Measured on uniform
points (n = 10^4 and 10^5, default tau and floor) kNNRefine's mesh has

    m / n = 2.3 / (k - 1.47)            (k >= 2, within 5% from k = 2 to 100)

vertices. Where k points fall within the resolution floor (duplicates, rounded coordinates,
and every point when k = 1) the mesh refines around them down to the floor instead: about 29
vertices per halving from the local spacing down to min_size, less the first four
(``floored_per_site``; measured: k = 1 on uniform points, 354 vertices per point at a
spacing 10^4.8 times min_size). ``estimate`` adds both
parts, the second from a sample of the points. It is a planning figure: within 5% on uniform
points, within 0.6 to 1.3 of the truth on most real data sets, but down to 0.13 on data with
tight clusters above the floor and up to 3.2 with many exact repeats
(``benchmarks/mesh_size.py``); it is reported in ``Mesh.stats["estimated_vertices"]``.

In space the same shape holds with other constants (measured on uniform points, n = 2 x 10^4,
the 3-torus): m / n = 3.2 / (k - 1.47) within 5% for k = 3 to 100 (6.0 against 7.2 at
k = 2), and about 215 vertices per point and halving (less the first four and a half) where
points are refined to the floor (k = 1: 2,190 vertices per point at a spacing 10^4.4 times
min_size).
"""

import os

import numpy as np

from .index import holds_k_within
from .index3 import holds_k_within3

PER_POINT = 2.3  # vertices per point times (k - 1.47), uniform data
K_SHIFT = 1.47
PER_POINT3 = 3.2  # the same in space
# vertices around a site refined to the floor, by the halvings from the points' spacing down
# to min_size (k = 1 on 60 and 200 uniform points, floors 10^-2 to 10^-6 of the box):
# SLOPE * (octaves - SHIFT) once the octaves are many, LOW * octaves when few
FLOORED = {2: (28.8, 3.75, 6.5), 3: (215.0, 4.45, 40.0)}  # dimension: (SLOPE, SHIFT, LOW)


def floored_per_site(octaves, dim):
    """Vertices around one site refined to the floor, ``octaves`` halvings below the points'
    spacing (2: the plane and the sphere, 3: space)."""
    slope, shift, low = FLOORED[dim]
    return max(slope * (octaves - shift), low * octaves)


BYTES_PER_VERTEX = 600  # peak memory of a run per mesh vertex (measured: 530 at k = 1, n = 1e5)
BYTES_PER_VERTEX3 = 1500  # in space (about 6.5 tetrahedra per vertex)
# on the sphere (tracemalloc's peak over a run, the index included: 300-420 bytes at
# n = 4e5 uniform points, k = 3-10)
BYTES_PER_VERTEX_SPHERE = 450
SAMPLE = 2000


def estimate(index, k, floor, lx, ly, area, seed=0):
    """Expected number of mesh vertices (on the torus) for the points in ``index``, and the
    fraction of points whose k-th neighbour lies within ``floor`` (internal units). ``area``
    is the area the points are spread over (the box's, internal units). For weighted points
    k is taken in units of their mean weight (whole weights are repeated points; the weights'
    scale does not matter, however small or large)."""
    pts = index.pts
    if pts.shape[0] == 0:
        return 0.0, 0.0
    n = pts.shape[0]
    if index.weight.shape[0]:  # weighted: k in units of the mean weight (the mesh depends on
        # k / weight, not on the weights' scale; tiny or huge weights stay finite here)
        total = float(index.weight[0])
        k_units = k * (n / total) if total > 0 else float(n)
    else:
        k_units = k
    rng = np.random.default_rng(seed)
    sample = pts[rng.choice(pts.shape[0], SAMPLE, replace=False)] if pts.shape[0] > SAMPLE else pts
    sample = np.ascontiguousarray(sample[:, :2])
    under = float(np.mean(holds_k_within(index, sample, np.full(len(sample), floor**2), k, lx, ly)))
    spacing = np.sqrt(area / n)
    octaves = max(1.0, float(np.log2(max(spacing / floor, 2.0))))
    k_units = min(max(k_units, 1e-300), float(n))
    regular = PER_POINT * n * (1.0 - under) / (k_units - K_SHIFT) if k_units >= 2 else 0.0
    floored = under * n / k_units * floored_per_site(octaves, 2)
    return regular + floored + 64.0, float(under)


def estimate3(index, k, floor, period, volume, seed=0):
    """``estimate`` in space: expected mesh vertices (on the 3-torus of ``period``) for the
    points of the 3-D ``index``, and the fraction of points whose k-th neighbour lies within
    ``floor``; ``volume`` the volume the points are spread over (internal units)."""
    pts = index.pts
    n = pts.shape[0]
    if n == 0:
        return 0.0, 0.0
    k_units = k
    if index.weight.shape[0]:  # weighted: k in units of the mean weight
        total = float(index.weight[0])
        k_units = k * (n / total) if total > 0 else float(n)
    rng = np.random.default_rng(seed)
    sample = pts[rng.choice(n, SAMPLE, replace=False)] if n > SAMPLE else pts
    sample = np.ascontiguousarray(sample[:, :3])
    r2 = np.full(len(sample), min(floor, 0.49 * float(np.min(period))) ** 2)
    under = float(np.mean(holds_k_within3(index, sample, r2, float(k),
                                          np.asarray(period, float))))  # fmt: skip
    spacing = (volume / n) ** (1.0 / 3.0)
    octaves = max(1.0, float(np.log2(max(spacing / floor, 2.0))))
    k_units = min(max(k_units, 1e-300), float(n))
    regular = PER_POINT3 * n * (1.0 - under) / (k_units - K_SHIFT) if k_units >= 2 else 0.0
    floored = under * n / k_units * floored_per_site(octaves, 3)
    return regular + floored + 64.0, float(under)


def expected_vertices(n, k, dim, octaves=17.0):
    """The size ``estimate`` (``estimate3``) expects of n uniform points in a torus, from
    their count alone (no index): PER_POINT (PER_POINT3) n / (k - K_SHIFT) for k >= 2, and at
    k = 1 every point refined around down to a floor ``octaves`` halvings below the
    spacing (17: the default floor, 10^-6 of the box, for 10^5 points in space)."""
    if k < 2:
        return n * floored_per_site(octaves, dim) + 64.0
    return (PER_POINT if dim == 2 else PER_POINT3) * n / (k - K_SHIFT) + 64.0


def memory_bytes():
    """The memory this process may use: physical memory, or the cgroup's limit if lower."""
    total = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            with open(path) as f:
                text = f.read().strip()
        except OSError:
            continue
        if text.isdigit():
            total = min(total, int(text))
    return int(total)

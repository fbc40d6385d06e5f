"""Small real data sets shipped with the package (sources and licences in data/README.md)."""

import gzip
from importlib import resources

import numpy as np

from ._validation import random_generator

TRP_BOX = (0.0, 0.0, 360.0, 360.0)
QUAKES_BOX = (-180.0, -90.0, 180.0, 90.0)


def _load(name):
    with resources.files("knnrefine.data").joinpath(name).open("rb") as f:
        with gzip.open(f, "rt") as text:
            return np.loadtxt(text, delimiter=",", skiprows=1)


def trp_chi1_chi2() -> np.ndarray:
    """Tryptophan side-chain torsions (chi1, chi2) in degrees from the Top8000 set, periodic
    with period 360 on both axes (box ``TRP_BOX``). CC BY 4.0, Williams et al. 2018.

    Returns
    -------
    ndarray (18748, 2)
    """
    return _load("trp_chi1_chi2.csv.gz")


def earthquakes() -> np.ndarray:
    """Epicentres (lon, lat) in degrees of the magnitude >= 5.5 earthquakes of 1965-2016;
    longitude is periodic (box ``QUAKES_BOX`` with ``periodic=(True, False)``). MIT licence
    (plotly/datasets).

    Returns
    -------
    ndarray (23412, 2)
    """
    return _load("quakes_1965_2016.csv.gz")


def ring(
    n: int = 2000,
    *,
    outliers: float = 0.2,
    random_state: int | np.random.Generator | np.random.RandomState | None = 0,
) -> np.ndarray:
    """A synthetic noisy circle of radius 1 with a fraction of uniform outliers in
    [-1.5, 1.5]^2: the persistence showcase (its loop survives the outliers at k = 30).

    Parameters
    ----------
    n : int
        Points in all.
    outliers : float
        Their share that is uniform.
    random_state : None, int, numpy Generator or RandomState

    Returns
    -------
    ndarray (n, 2)
    """
    rng = random_generator(random_state)
    m = int(round(n * (1 - outliers)))
    angle = rng.random(m) * 2 * np.pi
    circle = np.column_stack([np.cos(angle), np.sin(angle)]) + rng.normal(0, 0.03, (m, 2))
    return np.concatenate([circle, rng.uniform(-1.5, 1.5, (n - m, 2))])


def blobs(
    *, random_state: int | np.random.Generator | np.random.RandomState | None = 0
) -> np.ndarray:
    """Synthetic clusters: four Gaussian blobs of different widths (2,000 points each) on a
    uniform background of 2,000 points in the unit square.

    Parameters
    ----------
    random_state : None, int, numpy Generator or RandomState

    Returns
    -------
    ndarray (10000, 2)
    """
    rng = random_generator(random_state)
    centres = np.array([[0.2, 0.2], [0.8, 0.3], [0.5, 0.8], [0.2, 0.75]])
    widths = [0.04, 0.05, 0.03, 0.06]
    parts = [rng.normal(c, w, (2000, 2)) for c, w in zip(centres, widths, strict=True)]
    return np.concatenate(parts + [rng.random((2000, 2))])

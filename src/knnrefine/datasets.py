"""Small real data sets shipped with the package (sources and licences in data/README.md)."""

import gzip
from importlib import resources

import numpy as np

TRP_BOX = (0.0, 0.0, 360.0, 360.0)


def trp_chi1_chi2():
    """Tryptophan side-chain torsions (chi1, chi2) in degrees from the Top8000 set: (18748, 2),
    periodic with period 360 on both axes (box ``TRP_BOX``). CC BY 4.0, Williams et al. 2018."""
    with resources.files("knnrefine.data").joinpath("trp_chi1_chi2.csv.gz").open("rb") as f:
        with gzip.open(f, "rt") as text:
            return np.loadtxt(text, delimiter=",", skiprows=1)

"""Clustering through the mesh against clustering the points directly.

    python benchmarks/cluster_compare.py

On the clustered data sets of ../shared/data (Franti S1: 15 Gaussian clusters, Birch1: 100 on
a grid, Worms_2d: 35 thin curved bands, Old Faithful: 2), the same run times:

* knnrefine: refine(points, k) then knnrefine.cluster (ToMATo on the mesh graph with the log
  kNN density at the vertices; the peaks more prominent than the significance threshold
  2 sqrt(ln(n / k) / k)), k = sqrt(n) / 2;
* gudhi's ToMATo on the points (10-NN graph, log-DTM density with the same k), cut at the
  number of clusters knnrefine found;
* scikit-learn DBSCAN (min_samples 10, eps the 90th percentile of the 10th-neighbour
  distances) and HDBSCAN (min_cluster_size n / 200).

Agreement is the adjusted Rand index with knnrefine's labels (points DBSCAN and HDBSCAN call
noise get a label of their own).

Then ``counts``: how many clusters knnrefine finds where the truth is known (one Gaussian
blob, uniform noise, three blobs of unequal widths, two moons, S1, Birch1), at several k, with
the largest prominence it discarded over the threshold (below 1: the rule has room).
"""

import os
import time

import numpy as np

import knnrefine
from knnrefine.density import default_k

DATA = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "shared", "data")
SETS = ["franti_s1.csv", "franti_birch1.csv", "franti_worms2.csv", "old_faithful.csv"]


def main():
    from gudhi.clustering.tomato import Tomato
    from scipy.spatial import cKDTree
    from sklearn.cluster import DBSCAN, HDBSCAN
    from sklearn.metrics import adjusted_rand_score

    knnrefine.refine(np.random.default_rng(0).random((500, 2)), 10)  # warm the kernels
    print("| data set | n | method | clusters | noise | ARI with knnrefine | seconds |")
    print("|---|---:|---|---:|---:|---:|---:|")
    for name in SETS:
        path = os.path.join(DATA, name)
        if not os.path.exists(path):
            print(f"(skipping {name}: not available)")
            continue
        pts = np.loadtxt(path, delimiter=",", skiprows=1)
        if name == "old_faithful.csv":  # minutes against minutes: put both axes on one scale
            pts = (pts - pts.mean(0)) / pts.std(0)
        n = len(pts)
        k = default_k(n)
        t0 = time.perf_counter()
        mesh = knnrefine.refine(pts, k)
        ours = knnrefine.cluster(mesh, pts)
        rows = [("knnrefine (mesh ToMATo)", ours.labels, time.perf_counter() - t0)]
        t0 = time.perf_counter()
        direct = Tomato(
            graph_type="knn", density_type="logDTM", k=10, k_DTM=k, n_clusters=ours.n_clusters
        ).fit(pts)
        rows.append(("ToMATo on the points", direct.labels_, time.perf_counter() - t0))
        t0 = time.perf_counter()
        eps = float(np.percentile(cKDTree(pts).query(pts, k=[10])[0][:, 0], 90))
        rows.append(
            ("DBSCAN", DBSCAN(eps=eps, min_samples=10).fit(pts).labels_, time.perf_counter() - t0)
        )
        t0 = time.perf_counter()
        rows.append(
            (
                "HDBSCAN",
                HDBSCAN(min_cluster_size=max(5, n // 200), copy=True).fit(pts).labels_,
                time.perf_counter() - t0,
            )
        )
        for method, labels, seconds in rows:
            labels = np.asarray(labels)
            noise = float((labels < 0).mean())
            clusters = len(np.unique(labels[labels >= 0]))
            ari = adjusted_rand_score(ours.labels, labels)
            print(
                f"| {name.removesuffix('.csv')} | {n} | {method} | {clusters} | "
                f"{noise:.1%} | {ari:.3f} | {seconds:.2f} |",
                flush=True,
            )


def counts():
    from sklearn.datasets import make_moons

    rng = np.random.default_rng(1)
    unequal = np.concatenate(
        [rng.normal(c, w, (500, 2)) for c, w in (([0, 0], 1.0), ([8, 0], 2.5), ([3, 6], 0.5))]
    )
    cases = [
        ("one Gaussian blob", np.random.default_rng(0).normal(0, 1, (20_000, 2)), 1),
        ("uniform noise", np.random.default_rng(0).random((20_000, 2)), 1),
        ("three blobs, widths 1 / 2.5 / 0.5", unequal, 3),
        ("two moons (noise 0.06)", make_moons(2000, noise=0.06, random_state=0)[0], 2),
    ]
    for name, truth in (("franti_s1.csv", 15), ("franti_birch1.csv", 100)):
        path = os.path.join(DATA, name)
        if os.path.exists(path):
            cases.append(
                (name.removesuffix(".csv"), np.loadtxt(path, delimiter=",", skiprows=1), truth)
            )
    print()
    print("| points | n | truth | k | clusters found | largest discarded prominence / threshold |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, pts, truth in cases:
        n = len(pts)
        for k in sorted({default_k(n), 20, 50, 100}):
            cl = knnrefine.cluster(knnrefine.refine(pts, k), pts)
            discarded = cl.prominence[cl.n_clusters] if len(cl.prominence) > cl.n_clusters else 0
            print(
                f"| {name} | {n:,} | {truth} | {k}{' (default)' if k == default_k(n) else ''} | "
                f"{cl.n_clusters} | {discarded / cl.threshold:.2f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
    counts()

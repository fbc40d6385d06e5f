"""Pictures of a mesh with matplotlib: the input points, the triangles, and the triangles or the
Voronoi cells coloured by d_{M,2} (log scale). Periodic meshes are drawn across the seam."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from ._metric import BoxMetric, lonlat_of, unit_vectors
from ._validation import as_sphere_points
from .errors import InputError
from .mesh import edges

if TYPE_CHECKING:
    from .mesh import Mesh

__all__ = [
    "plot_mesh",
    "plot_sphere_mesh",
    "plot_orthographic",
    "plot_density",
    "plot_projections",
    "plot_slices",
    "plot_clusters",
    "plot_clusters_projected",
    "plot_diagram",
    "hdr_levels",
    "save_plot",
    "save_slices",
    "save_figure",
]


def plot_mesh(
    mesh: Mesh,
    points: Any = None,
    *,
    ax: Any = None,
    cells: str = "triangles",
    show_mesh: bool = True,
    show_points: bool = True,
    max_points: int = 200_000,
    cmap: str = "viridis",
    title: str | None = None,
    labels: Sequence[str] = ("x", "y"),
    value_range: tuple[float, float] | None = None,
    show_colour_bar: bool = True,
) -> Any:
    """Draw ``mesh`` on ``ax`` (a new figure if None); returns the axes.

    cells: "triangles" (coloured by d_{M,2} at their centroid), "voronoi" (each vertex's cell
    coloured by d_{M,2} at the vertex, the distance to its nearest other vertex) or "none".
    value_range: (low, high) of the colour scale (default: the values drawn), so that parts
    drawn on one axes share it; show_colour_bar: draw its bar.
    """
    from matplotlib.collections import LineCollection, PolyCollection
    from matplotlib.colors import LogNorm

    if cells not in ("triangles", "voronoi", "none"):
        raise InputError(f"cells must be 'triangles', 'voronoi' or 'none', got {cells!r}")
    if mesh.on_sphere:
        return plot_sphere_mesh(mesh, points, ax=ax, cells=cells, show_mesh=show_mesh,
                                show_points=show_points, max_points=max_points, cmap=cmap,
                                title=title, show_colour_bar=show_colour_bar)  # fmt: skip
    if ax is None:
        from matplotlib.figure import Figure

        ax = Figure(figsize=figure_size(mesh), layout="constrained").add_subplot()
    lo = np.array(mesh.extent[:2])
    hi = np.array(mesh.extent[2:])
    nodes, covering = mesh.covering()
    tris = nodes[covering]
    norm = None
    if cells == "triangles":
        values = mesh.d_m2(tris.mean(axis=1))
        polys, values = tris, values
    elif cells == "voronoi":
        polys, values = _voronoi_cells(mesh, lo, hi)
    if cells != "none":
        values = np.maximum(values, np.min(values[values > 0]) if (values > 0).any() else 1.0)
        low, high = (values.min(), values.max()) if value_range is None else value_range
        norm = LogNorm(vmin=low, vmax=max(high, low * 1.0001))
        # face-coloured hairlines close the antialiasing seams between neighbouring polygons
        coll = PolyCollection(
            polys,
            array=values,
            cmap=cmap,
            norm=norm,
            edgecolors="face",
            linewidths=0.3,
            rasterized=len(polys) > 20000,
        )
        ax.add_collection(coll)
        if show_colour_bar:
            colour_bar(ax, coll, f"$d_{{M,2}}$ (units of {labels[0]}, {labels[1]})")
    if show_mesh:
        pairs, _ = edges(covering)  # each edge once: equal alpha everywhere
        ax.add_collection(
            LineCollection(
                nodes[pairs],
                colors="0.1",
                alpha=0.45,
                linewidths=0.25 if len(tris) > 2000 else 0.5,
                rasterized=len(tris) > 20000,
            )
        )
    n = None
    if points is not None:
        pts = np.asarray(points, float)
        n = len(pts)
        if show_points:
            # at most a few points per mesh vertex, small and translucent: where the data is
            # dense the mesh is finest, and solid dots would hide it
            cap = min(max_points, 5 * len(mesh.vertices))
            if len(pts) > cap:
                pts = pts[np.random.default_rng(0).choice(len(pts), cap, replace=False)]
            pts = BoxMetric(mesh.box, mesh.periodic).wrap(pts)
            ax.scatter(
                pts[:, 0],
                pts[:, 1],
                s=0.8 if len(pts) > 5000 else 3,
                c="crimson",
                linewidths=0,
                alpha=0.35 if len(pts) > 5000 else 0.7,
                rasterized=True,
                label=f"input points{f' (a sample of {len(pts):,})' if n > len(pts) else ''}",
            )
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ratio = (hi[1] - lo[1]) / (hi[0] - lo[0])
    ax.set_aspect("equal" if 0.05 < ratio < 20 else "auto")
    ax.set_xlabel(labels[0])
    ax.set_ylabel(labels[1])
    if title is None:
        n = n if n is not None else mesh.stats.get("n")
        mode = {(True, True): ", periodic", (False, False): ""}.get(
            tuple(mesh.periodic), f", periodic in {'x' if mesh.periodic[0] else 'y'}"
        )
        title = (
            f"kNNRefine: n = {n:,}, k = {mesh.k}, tau = {mesh.tau:g}, m = {len(mesh.vertices):,}"
            f"{mode}; colour: distance to the second-nearest mesh vertex"
        )
    ax.set_title(title)
    return ax


def colour_bar(ax, mappable, label):
    """A colour bar exactly as tall as the axes' drawn area (an inset, so equal-aspect axes
    keep it), with ticks at 1, 2 and 5 times the powers of ten on log scales."""
    from matplotlib.colors import LogNorm
    from matplotlib.ticker import LogFormatterSciNotation, LogLocator

    cax = ax.inset_axes([1.03, 0.0, 0.035, 1.0])
    cbar = ax.figure.colorbar(mappable, cax=cax)
    if isinstance(mappable.norm, LogNorm):
        decades = np.log10(mappable.norm.vmax / mappable.norm.vmin)
        cbar.locator = LogLocator(subs=(1.0, 2.0, 5.0) if decades < 4 else (1.0,))
        cbar.formatter = LogFormatterSciNotation(labelOnlyBase=False)
        cbar.update_ticks()
    cbar.set_label(label)
    return cbar


def save_plot(
    mesh: Mesh,
    path: str | os.PathLike,
    points: Any = None,
    *,
    force: bool = False,
    dpi: int = 150,
    **kwargs: Any,
) -> None:
    """Draw the mesh and write the picture; PNG, SVG or PDF by the extension (a mesh on the
    sphere on an equal-area Mollweide map)."""
    save_figure(
        path,
        figure_size(mesh),
        lambda ax: plot_mesh(mesh, points, ax=ax, **kwargs),
        force=force,
        dpi=dpi,
        projection=MAP_PROJECTION if mesh.on_sphere else None,
    )


def save_figure(
    path: str | os.PathLike,
    figsize: tuple[float, float],
    draw: Callable,
    *,
    force: bool = False,
    dpi: int = 150,
    panels: int = 1,
    projection: str | None = None,
) -> None:
    """Make a figure, let ``draw(ax)`` fill it (``draw(axes)`` with a row of ``panels`` axes
    when more than one), write it atomically (PNG, SVG or PDF); ``projection``: matplotlib's
    (``"mollweide"`` for maps of the sphere)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from .io import atomic_write

    ext = os.path.splitext(path)[1].lower()
    if ext not in (".png", ".svg", ".pdf"):
        raise InputError(f"{path}: pictures are written as .png, .svg or .pdf")
    fig = Figure(figsize=figsize, layout="constrained")
    FigureCanvasAgg(fig)
    kw = {} if projection is None else {"projection": projection}
    draw(fig.add_subplot(**kw) if panels == 1 else list(fig.subplots(1, panels, subplot_kw=kw)))
    # tight: the colour bar inset and a long title stay in the picture
    atomic_write(
        path,
        force,
        lambda tmp: fig.savefig(tmp, dpi=dpi, format=ext[1:], bbox_inches="tight", pad_inches=0.1),
    )


HDR_MASSES = (0.5, 0.8, 0.95)  # the highest-density regions drawn by default
IMAGE_MASS = 0.99  # an image's colour scale reaches down to this region's level


def hdr_levels(values: Any, masses: Any = HDR_MASSES, *, areas: Any = None) -> np.ndarray:
    """The density levels whose superlevel sets hold the given shares of the mass of a grid
    of values: level t_p is the least value such that the cells at or above it hold p of the
    grid's total (Hyndman 1996's highest-density regions). Returns the levels, in the order
    of ``masses``.

    Parameters
    ----------
    values : ndarray
        Densities at the cells' centres (NaN and values <= 0 hold no mass).
    masses : sequence of float in (0, 1)
    areas : ndarray, optional
        The cells' areas, broadcast to ``values`` (default: equal cells; on a longitude by
        latitude grid, the cosine of the latitude).

    Returns
    -------
    ndarray
    """
    f = np.asarray(values, float)
    a = np.ones_like(f) if areas is None else np.broadcast_to(np.asarray(areas, float), f.shape)
    keep = np.isfinite(f) & (f > 0)
    f, a = f[keep], a[keep]
    order = np.argsort(f)[::-1]
    f, a = f[order], a[order]
    if len(f) == 0:
        raise InputError("the density is 0 or undefined everywhere on the grid: nothing to draw")
    share = np.cumsum(f * a) / (f * a).sum()
    masses = np.asarray(masses, float)
    if not np.all((masses > 0) & (masses < 1)):
        raise InputError(f"masses must lie in (0, 1), got {list(masses)}")
    return f[np.minimum(np.searchsorted(share, masses), len(f) - 1)]


def plot_density(
    density: Any,
    ax: Any,
    *,
    shape: int | tuple = (512, 512),
    labels: Sequence[str] | None = None,
    cmap: str | None = None,
    grid: tuple | None = None,
    style: str = "hdr",
    masses: Any = HDR_MASSES,
    points: Any = None,
    max_points: int = 20_000,
) -> Any:
    """Draw a density estimate the way statisticians publish one.

    Parameters
    ----------
    density : KnnDensityEstimator, KnnDensity or AdaptiveDensity
        A fitted estimator (drawn in the data's units, its columns' names as labels) or an
        estimate over a mesh's box.
    ax : matplotlib Axes
    shape : (ny, nx)
        The grid the density is evaluated on.
    labels : (str, str), optional
        The axes' names (default: the estimator's feature names, else "x", "y").
    cmap : str, optional
        A sequential colour map (default "Blues" for contours, "magma" for the image).
    grid : (xs, ys, values), optional
        The density on a grid already computed (then ``shape`` is not used).
    style : "hdr" or "image"
        "hdr": filled contours of the highest-density regions holding ``masses`` of the
        probability (50, 80 and 95% by default: the levels ``hdr_levels`` finds), as
        ``seaborn.kdeplot``'s filled contours, with their outlines; "image": the density as
        an image on a perceptual colour map, log scale from the peak down to the level of
        the region holding IMAGE_MASS of the mass (the tails beyond it, where single kernels
        would show, take the floor's colour).
    masses : sequence of float in (0, 1)
        The regions' shares of the mass ("hdr").
    points : array-like (n, 2), optional
        Points drawn over the density (at most ``max_points``, chosen at random).

    Returns
    -------
    matplotlib Axes

    Raises
    ------
    InputError
        An unknown style, or masses outside (0, 1).
    """
    from matplotlib import colormaps
    from matplotlib.colors import LogNorm

    if style not in ("hdr", "image"):
        raise InputError(f'style must be "hdr" or "image", got {style!r}')
    if _on_sphere(density):
        return _plot_sphere_density(density, ax, shape, cmap, grid, style, masses, points,
                                    max_points)  # fmt: skip
    xs, ys, f, box, names, title = _density_grid(density, shape, grid)
    labels = names if labels is None else labels
    extent = (box[0], box[2], box[1], box[3])
    if style == "hdr":
        order = np.argsort(masses)[::-1]  # widest region first
        masses = np.asarray(masses, float)[order]
        levels = hdr_levels(f, masses)
        top = float(np.nanmax(f))
        bounds = np.append(levels, top * (1 + 1e-9))
        colours = colormaps[cmap or "Blues"](np.linspace(0.35, 0.95, len(levels)))
        filled = ax.contourf(xs, ys, np.nan_to_num(f), levels=bounds, colors=colours)
        ax.contour(xs, ys, np.nan_to_num(f), levels=levels, colors=[colours[-1]],
                   linewidths=0.6)  # fmt: skip
        cbar = colour_bar(ax, filled, "highest-density region holding this share of the mass")
        cbar.set_ticks(0.5 * (bounds[:-1] + bounds[1:]))
        cbar.set_ticklabels([f"{m:.0%}" for m in masses])
    else:
        top = float(np.nanmax(f))
        floor = min(float(hdr_levels(f, [IMAGE_MASS])[0]), 0.1 * top)
        im = ax.imshow(
            np.where(np.isfinite(f) & (f > floor), f, floor), origin="lower", extent=extent,
            cmap=cmap or "magma", norm=LogNorm(vmin=floor, vmax=top, clip=True),
            interpolation="bilinear", aspect="auto",
        )  # fmt: skip
        colour_bar(ax, im, f"density per unit area ({labels[0]} by {labels[1]})")
    if points is not None:
        pts = np.asarray(points, float)
        if len(pts) > max_points:
            pts = pts[np.random.default_rng(0).choice(len(pts), max_points, replace=False)]
        ax.scatter(pts[:, 0], pts[:, 1], s=1.5, c="0.15", alpha=0.4, linewidths=0)
    ax.set_xlim(box[0], box[2])
    ax.set_ylim(box[1], box[3])
    ratio = (box[3] - box[1]) / (box[2] - box[0])
    ax.set_aspect("equal" if 0.05 < ratio < 20 else "auto")
    ax.set_xlabel(labels[0])
    ax.set_ylabel(labels[1])
    ax.set_title(title, fontsize="medium")
    return ax


def _density_grid(density, shape, grid):
    """(xs, ys, values, box, axis names, title) of a density to draw: a fitted
    ``KnnDensityEstimator`` in the data's units, or an estimate over its mesh's box."""
    xs, ys, f = density.grid(shape) if grid is None else grid
    if hasattr(density, "density_"):  # a fitted KnnDensityEstimator
        names = getattr(density, "feature_names_in_", None)
        names = tuple(names) if names is not None else ("x", "y")
        k, box = density.k_, density.box_
        what = "kNN density" if density.method_ == "knn" else "adaptive kernel density"
        knn = getattr(density.density_, "knn", density.density_)
    else:
        names = ("x", "y")
        knn = getattr(density, "knn", density)  # the adaptive estimate's pilot
        k = density.k
        what = "kNN density" if knn is density else "adaptive kernel density"
        box = knn.distance.mesh.extent
    m = len(knn.distance.mesh.vertices)
    effective = hasattr(density, "density_")
    return (
        xs,
        ys,
        np.asarray(f, float),
        box,
        names,
        (f"{what}\n{sample_label(knn, effective)}, k = {k}, m = {m:,}"),
    )


def sample_label(knn, effective=False):
    """ "n = 4,000" for an unweighted estimate; for a weighted one the points and their
    total weight, named: an estimator's weights sum to its effective sample size
    (``effective``), a user's to what they count."""
    points, total = knn.distance.n, float(knn.distance.total)
    if total == points:
        return f"n = {points:,}"
    what = "effective n" if effective else "total weight"
    total_text = f"{total:,.0f}" if total.is_integer() else f"{total:,.1f}"
    return f"n = {points:,} weighted ({what} {total_text})"


# -- the sphere -------------------------------------------------------------------------------
MAP_PROJECTION = "mollweide"  # equal-area, in matplotlib itself (no cartographic package)


def _on_sphere(density):
    """Whether a density (a KnnDensity, an AdaptiveDensity or a fitted estimator) lives on
    the sphere."""
    density = getattr(density, "density_", density)
    knn = getattr(density, "knn", density)
    distance = getattr(knn, "distance", None)
    return bool(getattr(distance, "on_sphere", False))


def _map_axes(ax, figsize=(10.0, 5.6)):
    """The axes to draw a map on: ``ax`` (a matplotlib geographic projection, such as
    ``projection="mollweide"``), or a new Mollweide figure's; a graticule every 30 degrees
    with labels, which reads without coastlines."""
    if ax is None:
        from matplotlib.figure import Figure

        ax = Figure(figsize=figsize, layout="constrained").add_subplot(projection=MAP_PROJECTION)
    if not hasattr(ax, "set_longitude_grid"):
        raise InputError(
            "a map of the sphere needs geographic axes: make them with "
            'fig.add_subplot(projection="mollweide") (or "hammer"), or use plot_orthographic'
        )
    ax.set_longitude_grid(30)
    ax.set_latitude_grid(30)
    ax.grid(True, color="0.5", linewidth=0.4, alpha=0.6)
    ax.tick_params(labelsize="small")
    return ax


def _projected(ax, lonlat):
    """Points (q, 2) in longitude and latitude (degrees) in the projected coordinates of the
    map axes ``ax``, all in one call of its projection; drawn with ``_after_projection(ax)``.
    matplotlib projects a collection path by path (contours, meshes, polygons), cutting
    every edge into many pieces: seconds for a map of a few thousand triangles."""
    return ax.transProjection.transform(np.radians(lonlat))


def _after_projection(ax):
    """The rest of the map axes' transform, for coordinates already ``_projected``."""
    return ax.transAffine + ax.transAxes


def _projected_polygons(ax, polygons, step=2.0):
    """Polygons in longitude and latitude (degrees), ``_projected``: matplotlib's own way
    (path by path, and again for the data limits) took 21 s for a 4,457-vertex mesh (8,910
    triangles) on a Mollweide map. An edge longer than ``step`` degrees is first cut into
    pieces of at most that (16 at most) so that it bends as the map does; an edge shared by
    two triangles is cut at the same points from both sides."""
    if not polygons:
        return []
    count = np.array([len(p) for p in polygons])
    start = np.repeat(np.cumsum(count) - count, count)
    corner = np.concatenate(polygons).astype(float)
    j = np.arange(len(corner))
    nxt = np.where(j + 1 - start == np.repeat(count, count), start, j + 1)
    length = np.hypot(*(corner[nxt] - corner).T)
    pieces = np.clip(np.ceil(length / step), 1, 16).astype(np.int64)
    edge = np.repeat(j, pieces)
    t = (np.arange(len(edge)) - np.repeat(np.cumsum(pieces) - pieces, pieces)) / pieces[edge]
    along = corner[edge] + t[:, None] * (corner[nxt[edge]] - corner[edge])
    flat = _projected(ax, along)
    ends = np.add.reduceat(pieces, np.cumsum(count) - count).cumsum()
    return np.split(flat, ends[:-1])


def plot_sphere_mesh(
    mesh: Mesh,
    points: Any = None,
    *,
    ax: Any = None,
    cells: str = "triangles",
    show_mesh: bool = True,
    show_points: bool = True,
    max_points: int = 200_000,
    cmap: str = "viridis",
    title: str | None = None,
    show_colour_bar: bool = True,
) -> Any:
    """Draw a mesh on the sphere on an equal-area map (Mollweide unless ``ax`` has another
    geographic projection): its triangles in longitude and latitude (``Mesh.pieces_in_box``:
    cut at the antimeridian), coloured by d_{M,2} at their centroids (log scale), the points
    over them. ``cells``: "triangles" or "none". Returns the axes."""
    from matplotlib.collections import PolyCollection
    from matplotlib.colors import LogNorm

    if cells not in ("triangles", "none"):
        raise InputError(f"cells must be 'triangles' or 'none' on the sphere, got {cells!r}")
    ax = _map_axes(ax)
    pieces = mesh.pieces_in_box()
    polys = _projected_polygons(ax, [p for _, p in pieces])
    if cells == "triangles" or show_mesh:
        if cells == "triangles":
            tri = np.array([t for t, _ in pieces])
            centroid = np.asarray(mesh.xyz)[mesh.triangles[tri]].sum(axis=1)
            values = mesh.d_m2(lonlat_of(centroid))
            values = np.maximum(values, values[values > 0].min() if (values > 0).any() else 1.0)
            norm = LogNorm(vmin=values.min(), vmax=max(values.max(), values.min() * 1.0001))
            coll = PolyCollection(polys, array=values, cmap=cmap, norm=norm,
                                  edgecolors="0.1" if show_mesh else "face",
                                  linewidths=0.15 if show_mesh else 0.3,
                                  rasterized=len(polys) > 20000,
                                  transform=_after_projection(ax))  # fmt: skip
        else:
            coll = PolyCollection(polys, facecolors="none", edgecolors="0.1", linewidths=0.2,
                                  rasterized=len(polys) > 20000,
                                  transform=_after_projection(ax))  # fmt: skip
        ax.add_collection(coll, autolim=False)  # a map's limits are the whole sphere
        if cells == "triangles" and show_colour_bar:
            unit = "radians" if mesh.radius == 1.0 else f"units of the radius {mesh.radius:g}"
            bar = ax.figure.colorbar(coll, ax=ax, shrink=0.7, pad=0.02)
            bar.set_label(f"$d_{{M,2}}$, great-circle ({unit})")
    if points is not None and show_points:
        pts = lonlat_of(as_sphere_points(points))
        if len(pts) > max_points:
            pts = pts[np.random.default_rng(0).choice(len(pts), max_points, replace=False)]
        ax.scatter(np.radians(pts[:, 0]), np.radians(pts[:, 1]), s=0.8, c="crimson",
                   linewidths=0, alpha=0.5, rasterized=True)  # fmt: skip
    if title is None:
        n = mesh.stats.get("n")
        title = (f"kNNRefine on the sphere: n = {n:,}, k = {mesh.k}, tau = {mesh.tau:g}, "
                 f"m = {len(mesh.vertices):,}")  # fmt: skip
    ax.set_title(title, fontsize="medium", pad=14)
    return ax


def _plot_sphere_density(density, ax, shape, cmap, grid, style, masses, points, max_points):
    """``plot_density`` on the sphere: an equal-area map of the density per unit area
    (steradian, or the radius' unit squared), its highest-density regions weighted by the
    cells' areas."""
    from matplotlib import colormaps
    from matplotlib.colors import LogNorm

    ax = _map_axes(ax)
    density = getattr(density, "density_", density)  # a fitted KnnDensityEstimator's
    knn = getattr(density, "knn", density)
    lon, lat, f = density.grid(shape) if grid is None else grid
    f = np.asarray(f, float)
    areas = np.cos(np.radians(lat))[:, None]
    # the grid projected once (path by path, the contours took 2.5 s of a world map's 4)
    lon2, lat2 = np.meshgrid(lon, lat)
    flat = _projected(ax, np.column_stack([lon2.ravel(), lat2.ravel()]))
    x, y = flat[:, 0].reshape(lon2.shape), flat[:, 1].reshape(lon2.shape)
    on_map = _after_projection(ax)
    if style == "hdr":
        order = np.argsort(masses)[::-1]
        masses = np.asarray(masses, float)[order]
        levels = hdr_levels(f, masses, areas=areas)
        top = float(np.nanmax(f))
        bounds = np.append(levels, top * (1 + 1e-9))
        colours = colormaps[cmap or "Blues"](np.linspace(0.35, 0.95, len(levels)))
        filled = ax.contourf(x, y, np.nan_to_num(f), levels=bounds, colors=colours,
                             transform=on_map)  # fmt: skip
        ax.contour(x, y, np.nan_to_num(f), levels=levels, colors=[colours[-1]], linewidths=0.6,
                   transform=on_map)  # fmt: skip
        bar = ax.figure.colorbar(filled, ax=ax, shrink=0.7, pad=0.02)
        bar.set_ticks(0.5 * (bounds[:-1] + bounds[1:]))
        bar.set_ticklabels([f"{m:.0%}" for m in masses])
        bar.set_label("highest-density region holding this share of the mass")
    else:
        top = float(np.nanmax(f))
        floor = min(float(hdr_levels(f, [IMAGE_MASS], areas=areas)[0]), 0.1 * top)
        mesh = ax.pcolormesh(x, y, np.where(np.isfinite(f) & (f > floor), f, floor),
                             cmap=cmap or "magma", norm=LogNorm(vmin=floor, vmax=top, clip=True),
                             shading="auto", rasterized=True, transform=on_map)  # fmt: skip
        radius = knn.distance.mesh.radius
        unit = "steradian" if radius == 1.0 else f"unit area (radius {radius:g})"
        bar = ax.figure.colorbar(mesh, ax=ax, shrink=0.7, pad=0.02)
        bar.set_label(f"density per {unit}")
    if points is not None:
        pts = lonlat_of(as_sphere_points(points))
        if len(pts) > max_points:
            pts = pts[np.random.default_rng(0).choice(len(pts), max_points, replace=False)]
        ax.scatter(np.radians(pts[:, 0]), np.radians(pts[:, 1]), s=1.0, c="0.15", alpha=0.4,
                   linewidths=0)  # fmt: skip
    k, m = knn.k, len(knn.distance.mesh.vertices)
    what = "kNN density" if knn is density else "adaptive kernel density"
    ax.set_title(f"{what} on the sphere\n{sample_label(knn)}, k = {k}, m = {m:,}",
                 fontsize="medium", pad=14)  # fmt: skip
    return ax


def plot_orthographic(
    mesh: Mesh,
    ax: Any = None,
    *,
    centre: tuple[float, float] = (0.0, 0.0),
    points: Any = None,
    cmap: str = "viridis",
    max_points: int = 50_000,
) -> Any:
    """The mesh on the sphere seen from far away above ``centre`` (longitude, latitude in
    degrees): the triangles of the facing hemisphere coloured by d_{M,2} (log scale), the
    points there over them. Returns the axes (ordinary, equal aspect)."""
    from matplotlib.collections import PolyCollection
    from matplotlib.colors import LogNorm

    if ax is None:
        from matplotlib.figure import Figure

        ax = Figure(figsize=(7.0, 6.0), layout="constrained").add_subplot()
    view = unit_vectors(np.array([centre], float))[0]
    east = np.cross([0.0, 0.0, 1.0], view)
    east = east / np.linalg.norm(east) if np.linalg.norm(east) > 1e-12 else np.array([0, 1.0, 0])
    north = np.cross(view, east)
    xyz = np.asarray(mesh.xyz)
    corners = xyz[mesh.triangles]
    facing = (corners @ view).min(axis=1) > 0
    flat = np.stack([corners[facing] @ east, corners[facing] @ north], axis=-1)
    values = mesh.d_m2(lonlat_of(corners[facing].sum(axis=1)))
    values = np.maximum(values, values[values > 0].min() if (values > 0).any() else 1.0)
    coll = PolyCollection(list(flat), array=values, cmap=cmap,
                          norm=LogNorm(vmin=values.min(), vmax=max(values.max(),
                                                                   values.min() * 1.0001)),
                          edgecolors="0.1", linewidths=0.15)  # fmt: skip
    ax.add_collection(coll)
    colour_bar(ax, coll, "$d_{M,2}$, great-circle")
    if points is not None:
        u = as_sphere_points(points)
        u = u[u @ view > 0]
        if len(u) > max_points:
            u = u[np.random.default_rng(0).choice(len(u), max_points, replace=False)]
        ax.scatter(u @ east, u @ north, s=0.8, c="crimson", linewidths=0, alpha=0.5)
    circle = np.linspace(0, 2 * np.pi, 361)
    ax.plot(np.cos(circle), np.sin(circle), color="0.2", linewidth=0.8)
    ax.set_xlim(-1.02, 1.02)
    ax.set_ylim(-1.02, 1.02)
    ax.set_aspect("equal")
    ax.set_axis_off()
    ax.set_title(f"seen from above ({centre[0]:g}, {centre[1]:g}): k = {mesh.k}, "
                 f"m = {len(mesh.vertices):,}", fontsize="medium")  # fmt: skip
    return ax


def plot_diagram(persistence: Any, ax: Any, *, dims: Sequence[int] = (0, 1)) -> Any:
    """Persistence diagram: birth against death per dimension; classes that never die on a
    line at the top."""
    colours = {0: "tab:blue", 1: "tab:orange", 2: "tab:green", 3: "tab:red"}
    finite = np.concatenate([persistence.diagram(d)[:, :2].ravel() for d in dims])
    finite = finite[np.isfinite(finite)]
    lo, hi = (finite.min(), finite.max()) if len(finite) else (0.0, 1.0)
    pad = 0.05 * (hi - lo if hi > lo else 1.0)
    top = hi + 3 * pad
    ax.plot([lo - pad, top], [lo - pad, top], color="0.5", lw=0.8)
    ax.axhline(top, color="0.7", lw=0.8, ls="--")
    for d in dims:
        dg = persistence.diagram(d)
        if len(dg) == 0:
            continue
        death = np.where(np.isfinite(dg[:, 1]), dg[:, 1], top)
        ax.scatter(
            dg[:, 0],
            death,
            s=12,
            color=colours.get(d, "k"),
            label=f"H{d} ({len(dg)})",
            alpha=0.8,
            edgecolors="none",
        )
    scale = "ln d_Pk (natural log)" if persistence.log else "d_Pk"
    ax.set_xlabel(f"birth ({scale})")
    ax.set_ylabel(f"death ({scale}); dashed: never dies")
    mesh = persistence.mesh
    ax.set_title(f"sublevel sets of d_Pk: k = {mesh.k}, m = {len(mesh.vertices)}")
    ax.legend(loc="lower right")
    ax.set_xlim(lo - pad, top + pad)
    ax.set_ylim(lo - pad, top + pad)
    ax.set_aspect("equal")
    return ax


def plot_clusters(
    mesh: Mesh,
    points: Any,
    labels: Any,
    ax: Any,
    *,
    max_points: int = 200_000,
    labels_xy: Sequence[str] = ("x", "y"),
) -> Any:
    """Input points coloured by cluster (noise, label -1, in grey) over the mesh's edges, with
    a legend of the clusters and their sizes; on the sphere, on a Mollweide map (``ax`` with
    that projection)."""
    pts = np.asarray(points, float)
    lab = np.asarray(labels)
    n_clusters = int(lab.max()) + 1 if len(lab) else 0
    sizes = np.bincount(lab[lab >= 0], minlength=n_clusters)
    noise = int((lab < 0).sum())
    if len(pts) > max_points:
        pick = np.random.default_rng(0).choice(len(pts), max_points, replace=False)
        pts, lab = pts[pick], lab[pick]
    title = (
        f"ToMATo on the mesh: {n_clusters} cluster{'s' if n_clusters != 1 else ''}"
        + (f" and {noise:,} noise points" if noise else "")
        + f", k = {mesh.k}, m = {len(mesh.vertices)}"
    )
    if mesh.on_sphere:  # an equal-area map: longitude and latitude in radians
        plot_mesh(mesh, None, ax=ax, cells="none", show_points=False, title=title)
        pts = np.radians(lonlat_of(as_sphere_points(pts)))
    else:
        plot_mesh(mesh, None, ax=ax, cells="none", show_points=False, labels=labels_xy,
                  title=title)  # fmt: skip
        pts = BoxMetric(mesh.box, mesh.periodic).wrap(pts)
    size = 2 if len(pts) > 5000 else 6
    if noise:
        grey = lab < 0
        ax.scatter(
            pts[grey, 0],
            pts[grey, 1],
            c="0.7",
            s=size,
            linewidths=0,
            rasterized=True,
            label=f"noise ({noise:,})",
        )
    palette = _palette(n_clusters)
    for c in range(n_clusters):
        mine = lab == c
        ax.scatter(
            pts[mine, 0],
            pts[mine, 1],
            color=palette[c],
            s=size,
            linewidths=0,
            rasterized=True,
            label=f"{c} ({sizes[c]:,})" if c < 20 else None,
        )
    extra = f" (first 20 of {n_clusters})" if n_clusters > 20 else ""
    ax.legend(
        title=f"cluster (points){extra}",
        loc="upper left",
        bbox_to_anchor=(1.02, 1.0),
        markerscale=8 if size < 4 else 2,
        fontsize="small",
        frameon=False,
    )
    return ax


def _palette(n):
    """n distinct, saturated colours: tab10, then tab20, then a hue wheel."""
    from matplotlib import colormaps

    if n <= 10:
        return [colormaps["tab10"](i) for i in range(n)]
    if n <= 20:
        return [colormaps["tab20"](i) for i in range(n)]
    return [colormaps["hsv"]((i * 0.618034) % 1.0) for i in range(n)]


def figure_size(mesh, width=9.0):
    """Inches for a picture of the box at equal aspect, with room for the colour bar."""
    w = mesh.extent[2] - mesh.extent[0]
    h = mesh.extent[3] - mesh.extent[1]
    ratio = min(max(h / w, 0.3), 1.6)
    return width, 1.0 + (width - 2.0) * ratio


def _voronoi_cells(mesh, lo, hi):
    """Voronoi cells of the vertices (and their periodic copies) that meet the box, from
    scipy; the picture's limits clip them."""
    from scipy.spatial import Voronoi

    period = np.array(mesh.period)
    sites = mesh.vertices
    shifts = [
        (sx, sy)
        for sx in ((-1, 0, 1) if mesh.periodic[0] else (0,))
        for sy in ((-1, 0, 1) if mesh.periodic[1] else (0,))
    ]
    cover = np.concatenate([sites + np.array(s) * period for s in shifts])
    own = np.tile(np.arange(len(sites)), len(shifts))
    vor = Voronoi(cover)
    spacing = mesh.d_m2(sites)  # at a vertex: the distance to its nearest other vertex
    polys, values = [], []
    span = hi - lo
    for i, region in enumerate(vor.point_region):
        verts = vor.regions[region]
        if not verts or -1 in verts:
            continue
        poly = vor.vertices[verts]
        if np.any(poly.max(0) < lo - 0.01 * span) or np.any(poly.min(0) > hi + 0.01 * span):
            continue
        polys.append(poly)
        values.append(spacing[own[i]])
    return polys, np.array(values)


# -- pictures of meshes in space: three views, one per pair of axes ---------------------------

#: the three views of a box in space: (horizontal axis, vertical axis, the axis across)
VIEWS = ((0, 1, 2), (0, 2, 1), (1, 2, 0))


def save_slices(
    mesh: Mesh,
    path: str | os.PathLike,
    points: Any = None,
    *,
    force: bool = False,
    dpi: int = 150,
) -> None:
    """A mesh in space as three slices through the box's centre coloured by d_{M,2}, with
    the points near each (``plot_slices``); PNG, SVG or PDF by the extension."""
    save_figure(
        path,
        space_figure_size(),
        lambda axes: plot_slices(
            mesh.d_m2,
            mesh,
            axes,
            "d_M2 (distance to the second-nearest vertex)",
            points=points,
            title=f"mesh in space: m = {len(mesh.vertices):,} vertices, "
            f"{len(mesh.cells):,} tetrahedra, k = {mesh.k}, tau = {mesh.tau:g}",
        ),
        force=force,
        dpi=dpi,
        panels=3,
    )


def space_figure_size(width=15.0):
    """Inches for three square views side by side, with room for colour bars."""
    return width, width / 3.0 + 0.6


def _view_extent(box, view):
    a, b, _ = view
    return (box[a], box[a + 3], box[b], box[b + 3])


def _points_near(points, box, periodic, axis, at, slab):
    """The points within ``slab`` of the plane ``x[axis] = at`` (in the box's metric)."""
    pts = BoxMetric(box, periodic).wrap(np.asarray(points, float))
    gap = np.abs(pts[:, axis] - at)
    if periodic[axis]:
        side = box[axis + 3] - box[axis]
        gap = np.minimum(gap, side - gap)
    return pts[gap <= slab]


def plot_slices(
    field: Callable,
    mesh: Any,
    axes: Any,
    label: str,
    *,
    points: Any = None,
    shape: int = 256,
    cmap: str = "viridis",
    title: str = "",
) -> Any:
    """Three slices of ``field`` (values at points (q, 3)) through the box's centre, one
    per pair of axes, log colour scale shared by the three, with the ``points`` (if given)
    within a slab of 1/50 of the box around each plane drawn as dots."""
    from matplotlib.colors import LogNorm

    box = np.asarray(mesh.box, float)
    centre = 0.5 * (box[:3] + box[3:])
    images = []
    for a, b, c in VIEWS:
        us = box[a] + (np.arange(shape) + 0.5) * (box[a + 3] - box[a]) / shape
        vs = box[b] + (np.arange(shape) + 0.5) * (box[b + 3] - box[b]) / shape
        q = np.empty((shape * shape, 3))
        q[:, a] = np.tile(us, shape)
        q[:, b] = np.repeat(vs, shape)
        q[:, c] = centre[c]
        images.append(np.asarray(field(q), float).reshape(shape, shape))
    finite = np.concatenate([im[np.isfinite(im) & (im > 0)] for im in images])
    norm = LogNorm(vmin=finite.min(), vmax=finite.max()) if len(finite) else None
    names = ("x", "y", "z")
    for ax, view, image in zip(axes, VIEWS, images, strict=True):
        a, b, c = view
        im = ax.imshow(image, origin="lower", extent=_view_extent(box, view), cmap=cmap,
                       norm=norm, interpolation="nearest", aspect="equal")  # fmt: skip
        if points is not None and len(points):
            slab = (box[c + 3] - box[c]) / 50.0
            near = _points_near(points, box, mesh.periodic, c, centre[c], slab)
            ax.scatter(near[:, a], near[:, b], s=2, c="white", linewidths=0, alpha=0.7,
                       rasterized=True)  # fmt: skip
        ax.set_xlabel(names[a])
        ax.set_ylabel(names[b])
        ax.set_title(f"{names[c]} = {centre[c]:.4g}", fontsize="small")
    colour_bar(axes[-1], im, label)
    if title:
        axes[0].figure.suptitle(title)
    return axes


def plot_projections(
    density: Any,
    axes: Any,
    *,
    grid: tuple | None = None,
    points: Any = None,
    max_points: int = 20_000,
    cmap: str = "magma",
) -> Any:
    """A density in space (``KnnDensity`` or ``AdaptiveDensity``) projected along each axis:
    the marginal density of each pair of axes (the grid summed across the third times its
    cell), log colour scale shared by the three, with up to ``max_points`` of the points as
    dots. ``grid``: (xs, ys, zs, values (nz, ny, nx)) when already computed."""
    from matplotlib.colors import LogNorm

    xs, ys, zs, f = density.grid() if grid is None else grid
    what = "adaptive kernel" if hasattr(density, "bandwidth") else "kNN"
    knn = getattr(density, "knn", density)  # the adaptive estimate's pilot knows the mesh
    mesh = knn.distance.mesh
    box = np.asarray(mesh.box, float)
    cell = (box[3:] - box[:3]) / (len(xs), len(ys), len(zs))
    # f is (z, y, x): the marginal of (x, y) sums over z, of (x, z) over y, of (y, z) over x
    marginals = [f.sum(axis=0) * cell[2], f.sum(axis=1) * cell[1], f.sum(axis=2) * cell[0]]
    finite = np.concatenate([m[np.isfinite(m) & (m > 0)] for m in marginals])
    norm = LogNorm(vmin=max(finite.min(), finite.max() * 1e-6), vmax=finite.max())
    if points is not None and len(points) > max_points:
        pick = np.random.default_rng(0).choice(len(points), max_points, replace=False)
        points = np.asarray(points)[pick]
    names = ("x", "y", "z")
    for ax, view, image in zip(axes, VIEWS, marginals, strict=True):
        a, b, _ = view
        im = ax.imshow(image, origin="lower", extent=_view_extent(box, view), cmap=cmap,
                       norm=norm, interpolation="nearest", aspect="equal")  # fmt: skip
        if points is not None:
            pts = BoxMetric(mesh.box, mesh.periodic).wrap(np.asarray(points, float))
            ax.scatter(pts[:, a], pts[:, b], s=1, c="white", linewidths=0, alpha=0.3,
                       rasterized=True)  # fmt: skip
        ax.set_xlabel(names[a])
        ax.set_ylabel(names[b])
    colour_bar(axes[-1], im, "marginal density")
    axes[0].figure.suptitle(
        f"{what} density projected along each axis: {sample_label(knn)}, k = {knn.k}, "
        f"m = {len(mesh.vertices):,}"
    )
    return axes


def plot_clusters_projected(
    mesh: Mesh, points: Any, labels: Any, axes: Any, *, max_points: int = 200_000
) -> Any:
    """Points in space coloured by cluster (noise in grey) in the three views of the box."""
    pts = BoxMetric(mesh.box, mesh.periodic).wrap(np.asarray(points, float))
    lab = np.asarray(labels)
    n_clusters = int(lab.max()) + 1 if len(lab) else 0
    if len(pts) > max_points:
        pick = np.random.default_rng(0).choice(len(pts), max_points, replace=False)
        pts, lab = pts[pick], lab[pick]
    palette = _palette(max(n_clusters, 1))
    colours = np.array(
        [palette[c] if c >= 0 else (0.7, 0.7, 0.7, 1.0) for c in range(-1, n_clusters)]
    )
    names = ("x", "y", "z")
    box = np.asarray(mesh.box, float)
    size = 1 if len(pts) > 5000 else 4
    for ax, (a, b, _) in zip(axes, VIEWS, strict=True):
        ax.scatter(pts[:, a], pts[:, b], c=colours[lab + 1], s=size, linewidths=0,
                   rasterized=True)  # fmt: skip
        ax.set_xlim(box[a], box[a + 3])
        ax.set_ylim(box[b], box[b + 3])
        ax.set_aspect("equal")
        ax.set_xlabel(names[a])
        ax.set_ylabel(names[b])
    noise = int((lab < 0).sum())
    axes[0].figure.suptitle(
        f"ToMATo on the mesh: {n_clusters} cluster{'s' if n_clusters != 1 else ''}"
        + (f" and {noise:,} noise points" if noise else "")
        + f", k = {mesh.k}, m = {len(mesh.vertices):,}"
    )
    return axes

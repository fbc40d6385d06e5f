"""Reading point files and writing meshes.

Points: CSV, TSV, semicolon- or whitespace-separated text with or without a header (pandas'
C parser), ``.npy``, ``.npz``, Parquet (with pyarrow), and ``-`` for standard input; two
columns chosen by name or by index.

Meshes: one writer per extension in ``WRITERS`` (and readers in ``READERS``):
``.npz`` is knnrefine's own, lossless format (everything ``certify`` needs); ``.vtu``,
``.vtk`` and ``.xdmf`` go through meshio for ParaView and friends (the whole mesh, with the
vertex copies beyond the box that its triangles use); ``.geojson`` for GIS (triangles cut to
the box, split at periodic seams); ``.csv`` lists the vertices inside the box. Writes go to
a temporary file that is renamed into place, so a failed or interrupted write never leaves
half a file; existing files are kept unless ``force``.
"""

from __future__ import annotations

import contextlib
import contextvars
import io as _io
import json
import os
import sys
import tempfile
import zipfile
import zlib
from collections.abc import Callable, Iterator

import numpy as np

from ._validation import check_radius
from .errors import InputError
from .mesh import Mesh, Torus

FORMAT_VERSION = 2  # 2: one layout for the plane and space (cells); 1 is still read
# what NumPy raises on a truncated or corrupted .npy / .npz (a zip of .npy members, each
# read, decompressed and parsed only when asked for)
UNREADABLE = (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error)


def unreadable(path: str | os.PathLike, what: str, exc: BaseException) -> InputError:
    """The InputError for a file NumPy could not read (``UNREADABLE``).

    Parameters
    ----------
    path : str or PathLike
    what : str
        The format (".npz").
    exc : BaseException
        What NumPy raised.

    Returns
    -------
    InputError
    """
    foreign = _not_numpys(path, what)
    if foreign is not None:
        return InputError(foreign)
    said = str(exc)
    if "pickle" in said:  # NumPy's advice to load pickles unsafely is not ours to give
        said = "it holds Python objects, not arrays"
    return InputError(
        f"{path}: not a readable {what} file: truncated or corrupted? ({type(exc).__name__}: "
        f"{said}); write it again"
    )


NUMPY_MAGIC = {".npy": (b"\x93NUMPY",), ".npz": (b"PK\x03\x04", b"PK\x05\x06")}


def _not_numpys(path, what):
    """What to say when the file is not NumPy's format at all (its first bytes are not an
    .npy header or a zip archive's): what it looks like instead; None when they are."""
    ext = ".npy" if ".npy" in what else ".npz"
    try:
        with open(path, "rb") as f:
            head = f.read(64)
    except OSError:
        return None
    if head.startswith(NUMPY_MAGIC[ext]):
        return None
    if not head:
        return f"{path}: the file is empty, not an {ext} file"
    text = head.decode("utf-8", "replace")
    printable = sum(c.isprintable() or c in "\r\n\t" for c in text) >= 0.95 * len(text)
    if printable:
        first = text.splitlines()[0][:40] if text.splitlines() else ""
        return (f"{path} is not an {ext} file but text (it starts {first!r}): name a CSV or "
                "text file by its own extension (.csv, .txt)")  # fmt: skip
    return f"{path} is not an {ext} file (its first bytes are not NumPy's {ext} header)"


# --- points -------------------------------------------------------------------------------


def read_points(
    path: str | os.PathLike, columns: str | None = None, delimiter: str | None = None
) -> np.ndarray:
    """Read points from CSV/TSV/text, .npy, .npz, .parquet or standard input ("-").

    Lines starting with ``#`` before the data are comments; a ``#`` anywhere else is data (a
    text field may hold one).

    Parameters
    ----------
    path : str or PathLike
    columns : str, optional
        Column names (``"lon,lat"``) or zero-based indices (``"2,3"``), two or three of them;
        default: the first two columns.
    delimiter : str, optional
        Default: sniffed from the first line (comma, tab, semicolon, else whitespace).

    Returns
    -------
    ndarray (n, d) float64

    Raises
    ------
    InputError
        A missing, unreadable or non-numeric file or column.
    """
    return read_points_named(path, columns, delimiter)[0]


def read_points_named(
    path: str | os.PathLike, columns: str | None = None, delimiter: str | None = None
) -> tuple[np.ndarray, tuple]:
    """``read_points``, and the columns' names.

    Parameters
    ----------
    path, columns, delimiter
        As for ``read_points``.

    Returns
    -------
    points : ndarray (n, d) float64
    names : tuple of str
        The header's (or the names given), else ("x", "y"[, "z"]).
    """
    return _read_columns(path, _parse_columns(columns), delimiter)


def read_weighted_points(
    path: str | os.PathLike,
    columns: str | None = None,
    weights: str | None = None,
    delimiter: str | None = None,
) -> tuple:
    """``read_points_named`` and a column of weights, read with the points (the weights'
    checks are the engine's).

    Parameters
    ----------
    path, columns, delimiter
        As for ``read_points``.
    weights : str, optional
        The weights' column, by name or zero-based index.

    Returns
    -------
    points : ndarray (n, d) float64
    weights : ndarray (n,) or None
    names : tuple of str
        The d columns' names.
    """
    cols = _parse_columns(columns)
    if weights is None:
        points, names = _read_columns(path, cols, delimiter)
        return points, None, names
    spec = str(weights).strip()
    if not spec or "," in spec:
        raise InputError(f"--weights needs one column, by name or index; got {weights!r}")
    cols = cols or [0, 1]
    dim = len(cols)
    table, names = _read_columns(path, cols + [_column(spec)], delimiter)
    return np.ascontiguousarray(table[:, :dim]), table[:, dim].copy(), names[:dim]


#: the columns' names where a file has none (the last stands for a weights column)
AXIS_NAMES = ("x", "y", "z", "w")


def _read_columns(path, cols, delimiter):
    """(array (n, len(cols)), the columns' names) of the file's columns ``cols`` (None: the
    first two)."""
    if path == "-":
        data = sys.stdin.buffer.read()
        return _read_text(_io.BytesIO(data), _io.BytesIO(data), "<stdin>", cols, delimiter)
    if not os.path.exists(path):
        raise InputError(f"{path}: no such file")
    if os.path.isdir(path):
        raise InputError(f"{path}: is a directory, not a file of points")
    ext = os.path.splitext(path)[1].lower()
    if cols is LONLAT and ext in (".npy", ".npz"):  # no names: the first two columns
        cols = None
    if ext == ".npy":
        points = _select_array(_load_npy(path), path, cols)
        return points, AXIS_NAMES[: points.shape[1]]
    if ext == ".npz":
        points = _read_npz_points(path, cols)
        return points, AXIS_NAMES[: points.shape[1]]
    if ext in (".parquet", ".pq"):
        return _read_parquet(path, cols)
    if not os.path.isfile(path):  # a pipe or a device: it can be read only once
        with open(path, "rb") as f:
            data = f.read()
        return _read_text(_io.BytesIO(data), _io.BytesIO(data), path, cols, delimiter)
    with open(path, "rb") as head:
        return _read_text(head, path, path, cols, delimiter)


LON_NAMES = ("lon", "lng", "long", "longitude")
LAT_NAMES = ("lat", "latitude")
LONLAT = "lonlat"  # ``columns``: the longitude and latitude columns, found by their names


def _parse_columns(columns):
    if columns is None:
        return None
    if isinstance(columns, str) and columns == LONLAT:
        return LONLAT
    if isinstance(columns, str):
        parts = [c.strip() for c in columns.split(",")]
    else:
        parts = list(columns)
    if len(parts) not in (2, 3) or not all(str(p) for p in parts):
        raise InputError(
            f"--columns needs two columns (lon,lat or 0,1), or three for points in space "
            f"(x,y,z); got {columns!r}"
        )
    return [_column(p) for p in parts]


def _column(spec):
    """A column given by zero-based index (an int, "2", "-1") or by name."""
    return int(spec) if str(spec).lstrip("-").isdigit() else str(spec)


def _sniff(first_line):
    for sep in (",", "\t", ";"):
        if sep in first_line:
            return sep
    return r"\s+"


def _is_number(token):
    try:
        float(token)
        return True
    except ValueError:
        return False


def _read_text(head, source, name, cols, delimiter):
    """``head``: a binary stream to sniff the first data line from; ``source``: what pandas
    reads (a path, or the same bytes)."""
    import pandas as pd

    first = None
    skipped = 0  # comment and blank lines before the first line of the table
    for raw in head:
        line = raw.decode("utf-8-sig", errors="replace").strip()
        if line and not line.startswith("#"):
            first = line
            break
        skipped += 1
    if first is None:
        raise InputError(f"{name}: the file is empty: no points to read")
    sep = delimiter if delimiter else _sniff(first)
    tokens = [t.strip().strip('"') for t in (first.split() if sep == r"\s+" else first.split(sep))]
    header = None if all(_is_number(t) for t in tokens if t) else 0
    try:
        frame = pd.read_csv(
            source,
            sep=sep,
            header=header,
            skiprows=skipped,
            skip_blank_lines=True,
            encoding="utf-8-sig",
        )
    except pd.errors.ParserError as exc:
        raise InputError(f"{name}: malformed rows: {exc}".replace("\n", " ")) from None
    except pd.errors.EmptyDataError:
        raise InputError(f"{name}: the file holds a header but no points") from None
    except UnicodeDecodeError:
        raise InputError(f"{name}: not a text file of points (it is not UTF-8)") from None
    if len(frame) == 0:
        raise InputError(f"{name}: the file holds a header but no points")
    return _select_frame(frame, name, cols, header is not None, skipped)


def _select_frame(frame, name, cols, has_header, skipped=0):
    import pandas as pd

    if frame.shape[1] < 2:
        raise InputError(f"{name}: needs at least two columns (x and y), found {frame.shape[1]}")
    if cols is None:
        cols = [0, 1]
    if cols is LONLAT:
        cols = _lonlat_columns(frame, name, has_header)
    picked = []
    for c in cols:
        if isinstance(c, int):
            if not -frame.shape[1] <= c < frame.shape[1]:
                raise InputError(
                    f"{name}: column index {c} is out of range "
                    f"(the file has {frame.shape[1]} columns)"
                )
            picked.append(frame.columns[c])
        else:
            if not has_header:
                raise InputError(
                    f"{name}: has no header, so columns must be given by index "
                    f"(like 0,1), not by name ({c!r})"
                )
            if c not in frame.columns:
                raise InputError(
                    f"{name}: no column named {c!r}; columns are "
                    f"{', '.join(map(str, frame.columns))}"
                )
            picked.append(c)
    out = np.empty((len(frame), len(picked)))
    for j, c in enumerate(picked):
        col = frame[c]
        if not pd.api.types.is_numeric_dtype(col):
            num = pd.to_numeric(col, errors="coerce")
            bad = num.isna() & col.notna()
            if bad.any():
                row = int(np.argmax(bad.to_numpy()))
                line = row + 1 + (1 if has_header else 0) + skipped
                raise InputError(
                    f"{name}: non-numeric value {col.iloc[row]!r} in column {c!r}, line {line}"
                )
            col = num
        out[:, j] = col.to_numpy(dtype=np.float64, na_value=np.nan)
    names = tuple(str(c) for c in picked) if has_header else AXIS_NAMES[: len(picked)]
    return out, names


def _lonlat_columns(frame, name, has_header):
    """The longitude and latitude columns by name (``LON_NAMES``, ``LAT_NAMES``, any case);
    without a header the first two columns; a header without them is an error."""
    if not has_header:
        return [0, 1]
    lower = {str(c).strip().lower(): c for c in frame.columns}
    lon = next((lower[n] for n in LON_NAMES if n in lower), None)
    lat = next((lower[n] for n in LAT_NAMES if n in lower), None)
    if lon is None or lat is None:
        raise InputError(
            f"{name}: no longitude and latitude columns found by name (lon, lng, longitude; "
            f"lat, latitude); columns are {', '.join(map(str, frame.columns))}: name them "
            "with --columns LON,LAT"
        )
    return [lon, lat]


def _load_npy(path):
    try:
        return np.load(path, allow_pickle=False)
    except UNREADABLE as exc:
        raise unreadable(path, ".npy", exc) from None


def _select_array(arr, name, cols):
    if arr.ndim != 2 or arr.shape[1] < 2:
        raise InputError(f"{name}: needs an (n, 2) array (or more columns), got shape {arr.shape}")
    if cols is None:
        cols = [0, 1]
    if not all(isinstance(c, int) for c in cols):
        raise InputError(f"{name}: array columns are chosen by index, like 0,1")
    try:
        return np.ascontiguousarray(arr[:, cols], dtype=np.float64)
    except IndexError:
        raise InputError(
            f"{name}: column indices {cols} out of range for shape {arr.shape}"
        ) from None
    except (TypeError, ValueError):
        raise InputError(f"{name}: the array is not numeric (dtype {arr.dtype})") from None


def _read_npz_points(path, cols):
    try:
        with np.load(path, allow_pickle=False) as data:
            if "points" in data:
                arr = data["points"]
            elif len(data.files) == 1:
                arr = data[data.files[0]]
            else:
                raise InputError(
                    f"{path}: holds {', '.join(data.files)}; store the points as 'points'"
                )
    except InputError:
        raise
    except UNREADABLE as exc:
        raise unreadable(path, ".npz", exc) from None
    return _select_array(arr, path, cols)


def _read_parquet(path, cols):
    try:
        import pyarrow.parquet as pq
    except ImportError:
        raise InputError(
            "reading Parquet needs pyarrow: pip install 'knnrefine[parquet]'"
        ) from None
    try:
        frame = pq.read_table(path).to_pandas()
    except Exception as exc:  # pyarrow raises many types for a bad file
        raise InputError(f"{path}: not a readable Parquet file ({exc})") from None
    return _select_frame(frame, path, cols, True)


# --- meshes -------------------------------------------------------------------------------


def write_mesh(mesh: Mesh, path: str | os.PathLike, *, force: bool = False) -> None:
    """Write a mesh in the format its extension names (``WRITERS``; in space ``WRITERS3``),
    atomically.

    Parameters
    ----------
    mesh : Mesh
    path : str or PathLike
    force : bool
        Overwrite an existing file.

    Raises
    ------
    InputError
        An extension the mesh's dimension is not written as, an existing file without
        ``force``, a folder that cannot be written.
    """
    writers = WRITERS3 if mesh.dim == 3 else WRITERS
    ext = os.path.splitext(path)[1].lower()
    if ext not in writers:
        what = "a mesh in space" if writers is WRITERS3 else "a mesh"
        raise InputError(f"{path}: {what} is written as {', '.join(sorted(writers))}, not {ext!r}")
    atomic_write(path, force, lambda tmp: writers[ext](mesh, tmp))


def read_mesh(path: str | os.PathLike) -> Mesh:
    """Read a mesh written by ``write_mesh`` as ``.npz`` (the lossless format), in the plane
    or in space, format 2 or 1.

    Parameters
    ----------
    path : str or PathLike

    Returns
    -------
    Mesh

    Raises
    ------
    InputError
        A missing, truncated or foreign file.
    """
    ext = os.path.splitext(path)[1].lower()
    if ext not in READERS:
        raise InputError(f"{path}: knnrefine reads meshes from {', '.join(READERS)} files")
    if not os.path.exists(path):
        raise InputError(f"{path}: no such file")
    return READERS[ext](path)


_batch: contextvars.ContextVar[list | None] = contextvars.ContextVar(
    "knnrefine_batch", default=None
)


@contextlib.contextmanager
def all_or_none() -> Iterator[None]:
    """Writes (``atomic_write`` and every writer here) inside this block are staged in
    temporary files beside their paths and put in place together when it ends without an
    error: then every file is written, or none (files they replace are kept aside until all
    are in place and put back if one fails). An error in the block, or in putting them in
    place, removes them all and is raised. The command line runs each command in one.

    Returns
    -------
    context manager
        ``with io.all_or_none(): ...`` (it yields nothing).

    Raises
    ------
    InputError
        A staged file that could not be put in place (its path a folder, say).
    """
    staged: list = []
    token = _batch.set(staged)
    try:
        yield
    except BaseException:
        _batch.reset(token)
        for tmp, _ in staged:
            _remove_quietly(tmp)
        raise
    _batch.reset(token)
    _commit(staged)


def _commit(staged):
    """Rename each staged (tmp, path) into place; on a failure undo those done (the files
    they replaced put back) and remove the rest."""
    done = []  # (path, the file it replaced, moved aside, or None)
    try:
        for tmp, path in staged:
            aside = None
            if os.path.isdir(path):
                raise InputError(f"{path} is a folder: give a file name")
            if os.path.lexists(path):
                aside = tmp + ".replaced"
                os.replace(path, aside)
            done.append((path, aside))
            os.replace(tmp, path)
    except BaseException as exc:
        for path, aside in reversed(done):
            if aside is None or os.path.lexists(aside):
                _remove_quietly(path)
            if aside is not None and os.path.lexists(aside):
                os.replace(aside, path)
        for tmp, _ in staged:
            _remove_quietly(tmp)
        if isinstance(exc, OSError):
            where = done[-1][0] if done else staged[0][1]
            raise InputError(f"{where}: could not be written ({exc.strerror or exc}); no "
                             "output was written") from None  # fmt: skip
        raise
    for _, aside in done:
        if aside is not None:
            _remove_quietly(aside)


def _remove_quietly(path):
    with contextlib.suppress(OSError):
        if os.path.lexists(path) and not os.path.isdir(path):
            os.remove(path)


def atomic_write(path: str | os.PathLike, force: bool, write: Callable) -> None:
    """Call ``write(tmp)`` on a temporary file beside ``path``, then rename it into place, so
    that a failed write leaves nothing behind (inside ``all_or_none``: renamed when the
    block ends, with the block's other files).

    Parameters
    ----------
    path : str or PathLike
    force : bool
        Overwrite an existing ``path``.
    write : callable
        Of the temporary file's path.

    Raises
    ------
    InputError
        An existing file without ``force``, a missing or read-only folder.
    """
    if os.path.isdir(path):
        raise InputError(f"{path} is a folder: give a file name")
    if os.path.exists(path) and not force:
        raise InputError(f"{path} exists; use --force (force=True) to overwrite it")
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise InputError(f"{path}: the folder {folder} does not exist")
    ext = os.path.splitext(path)[1]
    try:
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=".knnrefine-", suffix=ext)
    except OSError as exc:
        raise InputError(f"{path}: cannot write in {folder} ({exc.strerror})") from None
    os.close(fd)
    try:
        write(tmp)
        umask = os.umask(0)  # mkstemp makes the file private; give it the usual permissions
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        staged = _batch.get()
        if staged is not None:  # put in place when the block ends
            staged.append((tmp, os.fspath(path)))
            return
        os.replace(tmp, path)
    except OSError as exc:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise InputError(f"{path}: could not be written ({exc.strerror or exc})") from None
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def write_table(path: str | os.PathLike, columns: dict, *, force: bool = False) -> None:
    """A CSV file with a header line and one line per row, written atomically; floats with
    the fewest digits that read back to the same double (pandas' default), integers as
    integers.

    Parameters
    ----------
    path : str or PathLike
    columns : dict
        {name: array}, in order.
    force : bool
        Overwrite an existing file.
    """
    import pandas as pd

    frame = pd.DataFrame(dict(columns))
    atomic_write(path, force, lambda tmp: frame.to_csv(tmp, index=False))


def write_text(path: str | os.PathLike, text: str, *, force: bool = False) -> None:
    """A text file, written atomically.

    Parameters
    ----------
    path : str or PathLike
    text : str
    force : bool
        Overwrite an existing file.
    """
    atomic_write(path, force, lambda tmp: open(tmp, "w").write(text))


def _write_npz(mesh, path):
    """A mesh in the plane or in space, losslessly (``read_mesh`` gives it back, array for
    array, with the torus mesh ``certify`` checks); on the sphere with its unit vectors."""
    if mesh.on_sphere:
        with open(path, "wb") as f:
            np.savez_compressed(
                f, format=np.array(FORMAT_VERSION), domain=np.array("sphere"),
                radius=np.array(mesh.radius), vertices=mesh.vertices, xyz=mesh.xyz,
                cells=mesh.cells, kinds=mesh.kinds, order=mesh.order, k=np.array(mesh.k),
                tau=np.array(mesh.tau), min_size=np.array(mesh.min_size),
                floor_points=mesh.floor_points, stats=np.array(json.dumps(mesh.stats.to_dict())),
            )  # fmt: skip
        return
    t = mesh.torus
    d = mesh.dim
    neighbours = {} if t.neighbours is None else {"torus_neighbours": t.neighbours}
    with open(path, "wb") as f:
        np.savez_compressed(
            f,
            format=np.array(FORMAT_VERSION),
            vertices=mesh.vertices,
            cells=mesh.cells,
            offsets=mesh.offsets if mesh.offsets is not None else np.zeros((0, d + 1, d), np.int8),
            has_offsets=np.array(mesh.offsets is not None),
            kinds=mesh.kinds,
            order=mesh.order,
            k=np.array(mesh.k),
            tau=np.array(mesh.tau),
            periodic=np.array(mesh.periodic),
            box=np.array(mesh.box),
            min_size=np.array(mesh.min_size),
            floor_points=mesh.floor_points,
            stats=np.array(json.dumps(mesh.stats.to_dict())),
            torus_origin=np.array(t.origin),
            torus_period=np.array(t.period),
            torus_vertices=t.vertices,
            torus_cells=t.cells,
            torus_offsets=t.offsets,
            torus_kinds=t.kinds,
            **neighbours,
        )


def _read_npz(path):
    try:
        with np.load(path, allow_pickle=False) as d:
            return _mesh_of_npz(d, path)
    except InputError:
        raise
    except KeyError as exc:
        raise InputError(f"{path}: not a knnrefine mesh (missing {exc})") from None
    except UNREADABLE as exc:
        raise unreadable(path, ".npz mesh", exc) from None


def _mesh_of_npz(d, path):
    """The Mesh held by the open .npz ``d`` (every array read here): format 2 (one layout
    for both dimensions), or format 1 (the plane's, or space's ``Mesh3``)."""
    if int(d["format"]) > FORMAT_VERSION:
        raise InputError(f"{path}: written by a newer knnrefine (format {int(d['format'])})")
    if "tetrahedra" in d.files:
        return _mesh_of_space_format1(d)
    if "domain" in d.files and str(d["domain"]) == "sphere":
        return Mesh(
            vertices=d["vertices"], cells=d["cells"], offsets=None, kinds=d["kinds"],
            order=d["order"], k=d["k"].item(), tau=float(d["tau"]),
            periodic=(), box=(), min_size=float(d["min_size"]),  # no box (0.x wrote a chart's)
            floor_points=d["floor_points"], stats=json.loads(str(d["stats"])), torus=None,
            domain="sphere", radius=check_radius(float(d["radius"])), xyz=d["xyz"],
        )  # fmt: skip
    cells = "cells" if "cells" in d.files else "triangles"  # format 1: the plane's names
    torus = Torus(
        origin=tuple(d["torus_origin"].tolist()),
        period=tuple(d["torus_period"].tolist()),
        vertices=d["torus_vertices"],
        cells=d["torus_" + cells],
        offsets=d["torus_offsets"],
        kinds=d["torus_kinds"],
        neighbours=next(
            (d[key] for key in ("torus_neighbours", "torus_neighbors") if key in d.files), None
        ),  # files of knnrefine 0.1 spell it "neighbors"
    )
    return Mesh(
        vertices=d["vertices"],
        cells=d[cells],
        offsets=d["offsets"] if bool(d["has_offsets"]) else None,
        kinds=d["kinds"],
        order=d["order"],
        k=d["k"].item(),
        tau=float(d["tau"]),
        periodic=tuple(bool(p) for p in d["periodic"]),
        box=tuple(float(b) for b in d["box"]),
        min_size=float(d["min_size"]),
        floor_points=d["floor_points"],
        stats=json.loads(str(d["stats"])),
        torus=torus,
    )


def _mesh_of_space_format1(d):
    """A mesh in space written as format 1 (``Mesh3``: ``local`` vertices relative to
    ``origin``; the torus stored only when an axis was not periodic)."""
    offsets = d["offsets"] if bool(d["has_offsets"]) else None
    origin, period = tuple(d["origin"].tolist()), tuple(d["period"].tolist())
    if "torus_local" in d.files:
        torus = Torus(origin=origin, period=period, vertices=d["torus_local"],
                      cells=d["torus_tetrahedra"], offsets=d["torus_offsets"],
                      kinds=d["torus_kinds"])  # fmt: skip
        order = d["order"]
    else:
        torus = Torus(origin=origin, period=period, vertices=d["local"], cells=d["tetrahedra"],
                      offsets=offsets, kinds=d["kinds"])  # fmt: skip
        order = np.arange(len(d["vertices"]))
    return Mesh(
        vertices=d["vertices"], cells=d["tetrahedra"], offsets=offsets, kinds=d["kinds"],
        order=order, k=d["k"].item(), tau=float(d["tau"]),
        periodic=tuple(bool(p) for p in d["periodic"]),
        box=tuple(float(b) for b in d["box"]), min_size=float(d["min_size"]),
        floor_points=np.zeros((0, 3)), stats=json.loads(str(d["stats"])), torus=torus,
    )  # fmt: skip


def _meshio_writer(file_format):
    def write(mesh, path):
        import meshio

        if file_format == "xdmf":
            try:
                import h5py  # noqa: F401  (meshio's XDMF writer needs it even for XML data)
            except ImportError:
                raise InputError(
                    "writing .xdmf needs h5py: pip install 'knnrefine[xdmf]' "
                    "(or write .vtu, which needs nothing more)"
                ) from None

        if mesh.on_sphere:  # the triangles on the unit sphere
            out = meshio.Mesh(
                points=mesh.xyz,
                cells=[("triangle", mesh.triangles.astype(np.int64))],
                point_data={
                    "kind": mesh.kinds.astype(np.int32),
                    "order": mesh.order.astype(np.int64),
                    "d_m2": mesh.d_m2(mesh.vertices),
                    "longitude": mesh.vertices[:, 0],
                    "latitude": mesh.vertices[:, 1],
                },
            )
            kwargs = {"data_format": "XML"} if file_format == "xdmf" else {}
            meshio.write(path, out, file_format=file_format, **kwargs)
            return
        points, triangles, source = mesh.flat()
        out = meshio.Mesh(
            points=np.column_stack([points, np.zeros(len(points))]),
            cells=[("triangle", triangles.astype(np.int64))],
            point_data={
                "kind": mesh.kinds[source].astype(np.int32),
                "order": mesh.order[source].astype(np.int64),
                "d_m2": mesh.d_m2(points),
                "vertex": source.astype(np.int64),
            },
        )
        kwargs = {"data_format": "XML"} if file_format == "xdmf" else {}
        meshio.write(path, out, file_format=file_format, **kwargs)

    return write


def _write_geojson(mesh, path):
    """Triangles as Polygon features cut to the box (a triangle across a periodic seam
    becomes its pieces on either side: longitudes stay in the box, as WGS84 wants), with
    d_M2 at each piece's centroid and its triangle's index; parameters in the collection's
    properties. On the sphere, WGS84 longitude and latitude (``Mesh.pieces_in_box``: cut at
    the antimeridian, split at the poles), d_M2 in the mesh's length unit."""
    pieces = mesh.pieces_in_box()
    centroids = np.array([poly.mean(axis=0) for _, poly in pieces]).reshape(-1, 2)
    d = mesh.d_m2(centroids) if len(pieces) else np.zeros(0)
    with open(path, "w") as f:
        f.write('{"type": "FeatureCollection", "properties": ')
        f.write(
            json.dumps(
                {
                    "k": mesh.k,
                    "tau": mesh.tau,
                    "alpha": mesh.alpha,
                    "beta": mesh.beta,
                    **(
                        {"domain": "sphere", "radius": mesh.radius}
                        if mesh.on_sphere
                        else {"periodic": list(mesh.periodic), "box": list(mesh.box)}
                    ),
                }
            )
        )
        f.write(', "features": [\n')
        for i, (t, poly) in enumerate(pieces):
            ring = [[float(x), float(y)] for x, y in poly] + [
                [float(poly[0, 0]), float(poly[0, 1])]
            ]
            f.write(
                json.dumps(
                    {
                        "type": "Feature",
                        "geometry": {"type": "Polygon", "coordinates": [ring]},
                        "properties": {"d_m2": float(d[i]), "triangle": t},
                    }
                )
            )
            f.write(",\n" if i + 1 < len(pieces) else "\n")
        f.write("]}\n")


def _write_csv(mesh, path):
    """One row per vertex inside the box: vertex (its index in the mesh), x, y, kind (0
    initial, 1 circumball Break, 2 cell Break, 3 Clean), insertion order. The copies beyond
    a non-periodic side that the mesh keeps for its triangles are left out."""
    import pandas as pd

    if mesh.on_sphere:  # every vertex, in longitude and latitude
        pd.DataFrame({"vertex": np.arange(len(mesh.vertices)), "lon": mesh.vertices[:, 0],
                      "lat": mesh.vertices[:, 1], "kind": mesh.kinds,
                      "order": mesh.order}).to_csv(path, index=False)  # fmt: skip
        return
    lo, hi = np.array(mesh.box[:2]), np.array(mesh.box[2:])
    inside = np.flatnonzero(np.all((mesh.vertices >= lo) & (mesh.vertices <= hi), axis=1))
    pd.DataFrame(
        {
            "vertex": inside,
            "x": mesh.vertices[inside, 0],
            "y": mesh.vertices[inside, 1],
            "kind": mesh.kinds[inside],
            "order": mesh.order[inside],
        }
    ).to_csv(path, index=False)


def _meshio_writer3(file_format):
    """ParaView's view of a mesh in space: every tetrahedron with its corners where its
    offsets put them (vertex copies past the box's upper faces where a tetrahedron reaches
    there), each copy once; point data: kind, d_M2, the vertex it copies."""

    def write(mesh, path):
        import meshio

        o = (
            np.zeros((len(mesh.tetrahedra), 4, 3), np.int64)
            if mesh.offsets is None
            else mesh.offsets.astype(np.int64)  # 0 or 1: a tetrahedron spans under half a period
        )
        if o.max(initial=0) > 3:
            raise AssertionError("a tetrahedron's offsets reach past 3 periods")
        keys = mesh.tetrahedra.astype(np.int64) * 64 + o[..., 0] * 16 + o[..., 1] * 4 + o[..., 2]
        unique, inverse = np.unique(keys.ravel(), return_inverse=True)
        vertex = unique // 64
        shift = np.stack([unique // 16 % 4, unique // 4 % 4, unique % 4], 1)
        points = mesh.vertices[vertex] + shift * np.asarray(mesh.period)
        out = meshio.Mesh(
            points=points,
            cells=[("tetra", inverse.reshape(-1, 4).astype(np.int64))],
            point_data={
                "kind": mesh.kinds[vertex].astype(np.int32),
                "d_m2": mesh.d_m2(points),
                "vertex": vertex.astype(np.int64),
            },
        )
        meshio.write(path, out, file_format=file_format)

    return write


WRITERS3 = {".npz": _write_npz, ".vtu": _meshio_writer3("vtu"), ".vtk": _meshio_writer3("vtk")}

WRITERS = {
    ".npz": _write_npz,
    ".vtu": _meshio_writer("vtu"),
    ".vtk": _meshio_writer("vtk"),
    ".xdmf": _meshio_writer("xdmf"),
    ".geojson": _write_geojson,
    ".csv": _write_csv,
}
READERS = {".npz": _read_npz}

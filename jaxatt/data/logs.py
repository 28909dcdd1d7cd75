"""Plain IMU logs on disk: CSV and NPZ, read into / written from :class:`jaxatt.ImuSample` of numpy arrays.

Units and frames (never guessed; converted when the loader is told: ``gyr_unit``, ``acc_unit``, ``time_unit``,
:func:`jaxatt.frames.to_si`): time ``t`` in s; ``gyr`` angular rate in rad/s; ``acc`` specific force in m/s^2;
``mag`` magnetic field in the user's unit (uT, nT, gauss: keep it consistent with the observer's parameters); all
vectors in the sensor (body) frame. Optional ``quat_true``: ground-truth orientation, unit
quaternion (w, x, y, z), sensor-to-reference (e.g. ENU), NaN where unknown.

A missing reading is NaN (an empty CSV field, ``nan``, ``NA``, ``N/A`` or ``null`` reads as NaN); every observer
documents what it does with one.
Time must be finite and strictly increasing. Timestamps may also be dates and times: numpy ``datetime64`` (NPZ,
arrays) or ISO 8601 text such as ``2024-05-01 12:00:00.001`` (CSV; pandas writes them so) become seconds since the
first sample, and ``timedelta64`` durations become seconds, each from its own unit (ms, us, ns, ...).

CSV: one header line (comment lines starting with ``#`` may precede it) naming the columns (order free, extra
columns ignored; a column named nearly as one of the format's, ``magn_x`` or ``ACC_X``, is warned about; a
logger's own names are read through ``columns={"t": "time", "gyr_x": "GyroX", ...}`` / ``--columns``),
separated by commas, or by semicolons or tabs (the header line's separator is the file's; with a semicolon or a
tab, a decimal comma such as ``0,25`` is read as 0.25): ``t, gyr_x, gyr_y, gyr_z`` required (``t`` may be left
out when the sample period is given: ``dt=``, ``--dt``); ``acc_x, acc_y, acc_z`` and ``mag_x, mag_y, mag_z``
optional as groups of three; ``quat_w, quat_x, quat_y, quat_z`` optional. Numbers are written with 17
significant digits, so a float64 log survives a round trip exactly.

NPZ: arrays ``t`` (N,) (or ``dt=`` as for CSV), ``gyr`` (N, 3), optional ``acc`` (N, 3), ``mag`` (N, 3),
``quat_true`` (N, 4). Loaded without pickle.
"""

from __future__ import annotations

import csv
import difflib
import functools
import re
import warnings
import zipfile
from pathlib import Path
from typing import Dict, Mapping, Optional, Tuple, Union

import numpy as np

from .. import frames, io
from ..types import ImuSample

__all__ = [
    "load_log",
    "save_log",
    "load_csv",
    "save_csv",
    "load_npz",
    "load_trial",
    "save_npz",
    "check_log",
    "check_columns",
    "non_unit_row",
    "truth_gyro_agreement",
    "UNIT_TOLERANCE",
    "CSV_COLUMNS",
]

#: Largest | |q| - 1 | accepted in a quaternion that must be unit (ground truth, an estimate of
#: :func:`jaxatt.filter`); BROAD's truth and the registered observers stay within 1e-6.
UNIT_TOLERANCE = 1e-3


def non_unit_row(q, tol: float = UNIT_TOLERANCE) -> Optional[Tuple[int, float]]:
    """(row, norm) of the first finite row of ``q`` (N, 4) whose norm is off 1 by more than ``tol``; None if none
    (rows with NaN are skipped: a missing truth, or the caller's own non-finite check)."""
    q = np.asarray(q, np.float64)
    finite = np.all(np.isfinite(q), axis=-1)
    norm = np.linalg.norm(np.where(finite[:, None], q, 1.0), axis=-1)
    off = finite & (np.abs(norm - 1.0) > tol)
    if not off.any():
        return None
    k = int(np.argmax(off))
    return k, float(norm[k])


#: Column names of the CSV format (vector groups in x, y, z order).
CSV_COLUMNS = {
    "t": ("t",),
    "gyr": ("gyr_x", "gyr_y", "gyr_z"),
    "acc": ("acc_x", "acc_y", "acc_z"),
    "mag": ("mag_x", "mag_y", "mag_z"),
    "quat_true": ("quat_w", "quat_x", "quat_y", "quat_z"),
}


#: Other names of the time column that loggers write (compared in lower case, a unit such as " [s]" dropped).
TIME_ALIASES = ("time", "timestamp", "times", "time_s", "timestamp_s", "seconds", "sec", "elapsed")


def _lookalikes(want: str, header: list) -> list:
    """Header names that look like the format's column ``want`` but are not it: the same name in another case or
    with a unit attached (``ACC_X``, ``acc_x [m/s^2]``), a time alias for ``t``, or a close spelling (``magn_x``)."""
    names = {c for cols in CSV_COLUMNS.values() for c in cols}
    found = []
    for h in header:
        if h in names or not h:
            continue
        bare = re.split(r"[\s\[(]", h.strip().lower(), maxsplit=1)[0]
        close = difflib.SequenceMatcher(None, want, bare).ratio() >= 0.8
        if bare == want or close or (want == "t" and bare in TIME_ALIASES):
            found.append(h)
    return found


def narrow_timestamps_hint(dtype, t: np.ndarray) -> str:
    """ "; float32 timestamps near ... cannot resolve the sample interval: ..." when timestamps of a narrow float
    type (float32, float16) are large enough to be the reason two of them are equal; else ""."""
    if dtype not in (np.float32, np.float16) or not np.all(np.isfinite(t)) or np.max(np.abs(t)) <= 1e4:
        return ""
    return (
        f"; {np.dtype(dtype).name} timestamps near {np.max(np.abs(t)):.3g} s cannot resolve the sample interval: "
        "pass them as float64 or relative to the first"
    )


def check_timestamps(t, name: str = "t", dtype=None, where: str = "") -> None:
    """ValueError (one line) unless the timestamps ``t`` ((N,), s) are finite and strictly increasing, naming the
    first bad row of ``name``; ``where`` starts the message (e.g. "log walk.csv: "), ``dtype`` is the timestamps'
    type as given (a float32 hint). Every boundary that takes timestamps checks them here. Increasing timestamps
    of a narrow float type whose resolution is over 1 % of the sample interval are warned about (float32 at
    1e5 s steps by 0.0078 or 0.0156 s where the sensor stepped by 0.01 s)."""
    what = name
    t = np.asarray(t, np.float64)
    bad = ~np.isfinite(t)
    if bad.any():
        k = int(np.argmax(bad))
        raise ValueError(f"{where}{what} must be finite (s): {what}[{k}] is {float(t[k])}")
    d = np.diff(t)
    if not np.any(d <= 0):
        if dtype in (np.float32, np.float16) and d.size:
            top, step = float(np.max(np.abs(t))), float((t[-1] - t[0]) / d.size)  # the mean: the median is quantised
            resolution = float(np.spacing(np.asarray(top, dtype)))
            if resolution > 0.01 * step:
                warnings.warn(
                    f"{where}{what} is {np.dtype(dtype).name}: near {top:.3g} s it resolves {resolution:.3g} s, "
                    f"against a sample interval of {step:.3g} s (each step is off by up to half of that): pass the "
                    "timestamps as float64 or relative to the first",
                    stacklevel=3,
                )
        return
    k = int(np.argmax(d <= 0))
    hint = narrow_timestamps_hint(dtype, t)
    if not hint and d[k] == 0 and np.mean(d == 0) > 0.05 and np.any(d > 0):  # stamps coarser than the period
        step = float(np.median(d[d > 0]))
        hint = (
            f"; {int(np.sum(d == 0))} of {d.size} steps repeat a timestamp (they advance by {step:.3g} s): stamps "
            "rounded coarser than the sample period? give the sample period (dt) instead"
        )
    raise ValueError(
        f"{where}{what} must be strictly increasing (s): {what}[{k + 1}] = {t[k + 1]:.9g} after {what}[{k}] = "
        f"{t[k]:.9g}" + hint
    )


def check_log(samples: ImuSample, quat_true=None, *, source: str = "log") -> Tuple[ImuSample, Optional[np.ndarray]]:
    """Validate a log and return it as float64 numpy arrays.

    ``t`` may be ``datetime64`` (seconds since the first sample) or ``timedelta64`` (seconds), converted with
    their own unit. Raises ValueError if: ``t`` is not (N,) with N >= 1, not finite or not strictly increasing;
    ``gyr`` is not (N, 3); ``acc`` / ``mag`` (when present) are not (N, 3); ``quat_true`` (when present) is not
    (N, 4); a field is not real numbers (text, objects, bools, complex). NaN in gyr / acc / mag / quat_true is
    allowed (a missing reading); +-inf is not.
    """

    def arr(name, v, shape_tail):
        if np.iscomplexobj(v):
            raise ValueError(f"{source}: {name} is complex, expected real numbers")
        try:
            a = np.asarray(v)
            if name == "t" and a.dtype.kind in "Mm":
                a = timestamp_seconds(a)
            elif a.dtype.kind in "bOSUMm":  # bool, objects, text, dates and durations other than t
                raise ValueError(f"dtype {a.dtype}, expected real numbers")
            a = np.asarray(a, dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise ValueError(f"{source}: {name} is not numeric: {e}") from None
        if a.ndim != 1 + len(shape_tail) or a.shape[1:] != shape_tail:
            want = "(N," + "".join(f" {d}" for d in shape_tail) + ")"
            raise ValueError(f"{source}: {name} must have shape {want}, got {a.shape}")
        return a

    t_dtype = getattr(samples.t, "dtype", None)
    t = arr("t", samples.t, ())
    n = t.shape[0]
    if n < 1:
        raise ValueError(f"{source}: the log is empty")
    check_timestamps(t, "t", t_dtype, f"{source}: ")
    out = {"t": t}
    for name in ("gyr", "acc", "mag"):
        v = getattr(samples, name)
        if v is None:
            if name == "gyr":
                raise ValueError(f"{source}: gyr is required")
            out[name] = None
            continue
        a = arr(name, v, (3,))
        if a.shape[0] != n:
            raise ValueError(f"{source}: {name} has {a.shape[0]} rows but t has {n}")
        if np.any(np.isinf(a)):
            raise ValueError(f"{source}: {name} contains inf (use NaN for a missing reading)")
        out[name] = a
    q = None
    if quat_true is not None:
        q = arr("quat_true", quat_true, (4,))
        if q.shape[0] != n:
            raise ValueError(f"{source}: quat_true has {q.shape[0]} rows but t has {n}")
        if np.any(np.isinf(q)):
            raise ValueError(f"{source}: quat_true contains inf (use NaN where unknown)")
        bad = non_unit_row(q)
        if bad is not None:
            raise ValueError(
                f"{source}: quat_true (CSV columns quat_w ... quat_z) row {bad[0]} has norm {bad[1]:.6g}; the truth "
                "must be unit quaternions (w, x, y, z): normalise each row"
            )
    return ImuSample(out["t"], out["gyr"], out["acc"], out["mag"]), q


def timestamp_seconds(t: np.ndarray) -> np.ndarray:
    """datetime64 timestamps as float64 seconds since the first (NaT -> NaN), timedelta64 as seconds; each from its
    own unit. ValueError for units of no fixed length (months, years)."""
    if t.size == 0:
        return np.zeros(t.shape)
    dtype = t.dtype
    try:
        return (t - t.reshape(-1)[0] if dtype.kind == "M" else t) / np.timedelta64(1, "s")
    except TypeError:
        raise ValueError(f"{dtype} has no fixed length in seconds (use a unit of D or finer)") from None


# ------------------------------------------------------------------------------------------------------------
# CSV
# ------------------------------------------------------------------------------------------------------------
def _is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


#: Field separators a CSV log may use; the header line's decides (:func:`_separator`).
CSV_SEPARATORS = (",", ";", "\t")


def _separator(header_line: str) -> str:
    """The header line's field separator: the one of :data:`CSV_SEPARATORS` that splits it into the most fields
    (a comma on a tie)."""
    return max(CSV_SEPARATORS, key=lambda c: len(next(csv.reader([header_line], delimiter=c))))


def _parse_float(s: str, row: int, col: str, source: str, decimal_comma: bool = False) -> float:
    s = s.strip()
    if s == "" or s.lower() in MISSING_CELLS:
        return np.nan
    try:
        return float(s.replace(",", ".") if decimal_comma else s)
    except ValueError:
        raise ValueError(f"{source}: line {row}: column {col!r}: {_shown(s)} is not a number") from None


def _shown(cell: str, most: int = 40) -> str:
    """A cell as an error message shows it: its repr, cut to ``most`` characters (a quote left open swallows
    the lines after it into one cell)."""
    r = repr(cell)
    return r if len(r) <= most else r[: most - 5] + "...'" + f" ({len(cell)} characters)"


def _read_table_fast(f, columns: list, n_header: int, sep: str = ",") -> Optional[np.ndarray]:
    """The data rows' ``columns`` (indices) as a (rows, len(columns)) float array by numpy's C reader, or None
    when the file is not plain numbers with one field per header column on every row (an empty cell, a quoted
    field, a short or long row, a text column, a decimal comma): the checked reader then says where."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "input contained no data": handled by the checked reader
            table = np.loadtxt(f, delimiter=sep, ndmin=2, dtype=np.float64, comments=None)
    except (ValueError, IndexError):
        return None
    if not table.size or table.shape[1] != n_header:
        return None
    return table[:, columns]


def _read_table_checked(
    f, header: list, columns: list, src: str, sep: str = ",", first_line: int = 2
) -> Tuple[np.ndarray, bool]:
    """The data rows' ``columns`` cell by cell: empty cells are NaN, anything else that is not a number is an
    error naming its line (in the file: ``first_line`` is the first data row's) and column (with a semicolon or
    tab separator a decimal comma is a decimal point). Returns (table, whether ``t`` held date-times)."""
    reader = csv.reader(f, delimiter=sep)
    rows, lines, last = [], [], 0
    try:
        for r in reader:
            if r and any(c.strip() for c in r):
                rows.append(r)
                lines.append(first_line + last)  # the line the row starts on
            last = reader.line_num
    except csv.Error as e:
        raise ValueError(
            f'{src}: line {first_line + last}: cannot be read as CSV ({e}): is a quote (") left open there?'
        ) from None
    if not rows:
        raise ValueError(f"{src}: no data rows")
    table = np.empty((len(rows), len(columns)))
    need = max(columns) + 1
    for k, r in enumerate(rows):
        if len(r) < need or any(c.strip() for c in r[len(header) :]):  # short, or values beyond the header
            quote = ': a quote (") opened there is never closed' if any("\n" in c for c in r) else ""
            raise ValueError(f"{src}: line {lines[k]} has {len(r)} fields, header has {len(header)}{quote}")
    dated = False
    for j, i in enumerate(columns):
        cells = [r[i].strip() for r in rows]
        if header[i] == "t" and _datetime_column(cells):
            table[:, j] = _datetime_seconds(cells, src, lines)
            dated = True
            continue
        for k, c in enumerate(cells):
            table[k, j] = _parse_float(c, lines[k], header[i], src, decimal_comma=sep != ",")
    return table, dated


def _datetime_column(cells: list) -> bool:
    """Whether a column's first non-empty cell is an ISO 8601 date-time (and not a number)."""
    first = next((c for c in cells if c), "")
    if not first or _is_number(first) or first.lower() == "nat":
        return False
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # numpy: "no explicit representation of timezones"
            np.datetime64(first)
    except ValueError:
        return False
    return True


def _datetime_seconds(cells: list, src: str, lines: list) -> np.ndarray:
    """A CSV time column of ISO 8601 date-times as seconds since the first row (empty -> NaN: refused later)."""
    out = np.empty(len(cells), dtype="datetime64[ns]")
    for k, c in enumerate(cells):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # an offset such as +02:00 is applied (times in UTC)
                out[k] = np.datetime64(c, "ns") if c else np.datetime64("NaT")
        except ValueError:
            raise ValueError(
                f"{src}: line {lines[k]}: column 't': {_shown(c)} is not a date-time like the first row"
            ) from None
    return timestamp_seconds(out)


def _uniform_times(n: int, dt: Optional[float], src: str) -> np.ndarray:
    """t = 0, dt, 2 dt, ... (s) for a log without timestamps; ``dt`` must be a finite positive number."""
    try:
        if isinstance(dt, (bool, np.bool_, str, bytes)):  # True would be 1 s; "0.01" is text, not a number
            raise TypeError
        step = float(dt)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValueError(f"{src}: dt must be a number of seconds, got {dt!r}") from None
    if not (np.isfinite(step) and step > 0):
        raise ValueError(f"{src}: dt must be a finite positive number of seconds, got {dt!r}")
    return np.arange(n) * step


_NO_TIME_HINT = " (or give the sample period: dt= / --dt)"
_COLUMNS_READ = "; the columns read are t, gyr_x, gyr_y, gyr_z and the groups acc_*, mag_*, quat_* (x, y, z; w first)"
#: Cells read as a missing reading besides an empty one and nan (R's NA, spreadsheets' N/A, JSON's null).
MISSING_CELLS = frozenset({"na", "n/a", "null", "none"})


def check_columns(columns) -> Dict[str, str]:
    """``columns`` (a mapping, or text ``"gyr_x=GyroX,gyr_y=GyroY,..."``): which column of a CSV file holds each
    of the format's columns (:data:`CSV_COLUMNS`); ValueError naming the bad entry."""
    if columns is None:
        return {}
    if isinstance(columns, str):
        pairs = [p.strip() for p in columns.split(",") if p.strip()]
        if not pairs or any(p.count("=") != 1 for p in pairs):
            raise ValueError(f"columns must be 'name=column,...' (e.g. 'gyr_x=GyroX,t=time'), got {columns!r}")
        items = [(k.strip(), v.strip()) for k, v in (p.split("=") for p in pairs)]
        keys = [k for k, _ in items]
        twice = sorted({k for k in keys if keys.count(k) > 1})
        if twice:
            raise ValueError(f"columns: {twice[0]!r} is given more than once")
        columns = dict(items)
    if not isinstance(columns, Mapping):
        raise ValueError(f"columns must be a mapping of the format's column names to the file's, got {columns!r}")
    names = [c for cols in CSV_COLUMNS.values() for c in cols]
    for k, v in columns.items():
        if k not in names:
            turned = " (the names on the left are jaxatt's, on the right the file's)" if v in names else ""
            raise ValueError(f"columns: {k!r} is not one of the format's columns ({', '.join(names)}){turned}")
        if not isinstance(v, str) or not v:
            raise ValueError(f"columns: the file's column for {k!r} must be a name, got {v!r}")
    given = list(columns.values())
    twice = sorted({v for v in given if given.count(v) > 1})
    if twice:
        raise ValueError(f"columns: the file's column {twice[0]!r} is given for more than one of the format's columns")
    return dict(columns)


def load_csv(
    path,
    *,
    with_truth: bool = False,
    dt: Optional[float] = None,
    replace_t: bool = False,
    columns: Union[Mapping[str, str], str, None] = None,
    gyr_unit: str = "rad/s",
    acc_unit: str = "m/s^2",
    time_unit: str = "s",
):
    """Read a CSV log (see the module docstring). Returns ImuSample (or (ImuSample, quat_true or None)).

    ``dt`` (s): the sample period of a log without a ``t`` column (t = 0, dt, 2 dt, ...); a ``t`` column, when
    there is one, is read and ``dt`` is not used (``replace_t``: the column is not read and ``dt`` times the log).
    ``columns``: the file's names of the format's columns, e.g. ``{"t": "time", "gyr_x": "GyroX", ...}``
    (:func:`check_columns`); the file's own column of a name that ``columns`` maps elsewhere is not read.
    ``gyr_unit``, ``acc_unit``, ``time_unit``: the units of the file's gyro, accelerometer and time columns
    (:func:`jaxatt.frames.to_si`), converted to rad/s, m/s^2 and s (date-time stamps carry their own unit).
    Plain numeric files go through numpy's C reader; a file with
    empty cells (read as NaN) or anything unusual is read cell by cell, and a cell that is not a number is
    refused with its line and column."""
    _check_units(gyr_unit, acc_unit, time_unit)
    rename = {v: k for k, v in check_columns(columns).items()}
    path = Path(path)
    src = str(path)
    with open(path, newline="", encoding="utf-8-sig") as f:  # -sig: a byte-order mark (Excel's "CSV UTF-8")
        start, first, line, comment = f.tell(), f.readline(), 1, ""
        while first and (first.startswith("#") or not first.strip()):  # comments and blank lines above the header
            comment = first if first.startswith("#") else comment
            start, first, line = f.tell(), f.readline(), line + 1
        if not first.strip():
            raise ValueError(f"{src}: empty file (a header line is required)")
        sep = _separator(first)
        # skipinitialspace: a quoted name after ", " ("Time (ms)", "Gyro X") loses its quotes
        header = [h.strip() for h in next(csv.reader([first], delimiter=sep, skipinitialspace=True))]
        if any(header) and all(_is_number(h) for h in header if h):
            named = [h.strip() for h in next(csv.reader([comment.lstrip("#")], delimiter=sep))] if comment else []
            if "gyr_x" not in named:
                raise ValueError(
                    f"{src}: line {line} must be a header naming the columns (t, gyr_x, gyr_y, gyr_z, ...), got numbers"
                )
            header, line = named, line - 1  # numpy.savetxt's header: '# t,gyr_x,...' above the numbers
            f.seek(start)
        if len(set(header)) != len(header):
            raise ValueError(f"{src}: duplicate column names in the header: {header}")
        if rename:
            absent = [v for v in rename if v not in header]
            if absent:
                raise ValueError(f"{src}: column {absent[0]!r} (given in columns) is not in the header: {header}")
            mapped = set(rename.values())  # the file's own column of a mapped name is not read
            file_header, header = header, [rename.get(h, "" if h in mapped else h) for h in header]
        else:
            file_header = header
        if replace_t:
            _uniform_times(0, dt, src)  # dt must be given
            header = ["" if h == "t" else h for h in header]  # not read
        idx = {h: i for i, h in enumerate(header)}
        required = CSV_COLUMNS["gyr"] if dt is not None else CSV_COLUMNS["t"] + CSV_COLUMNS["gyr"]
        for c in required:
            if c not in idx:
                looks = _lookalikes(c, header)
                if rename and c in rename:  # the file's own column of that name is mapped onto another
                    raise ValueError(
                        f"{src}: required column {c!r} missing: the file's column {c!r} is read as {rename[c]!r} "
                        f"(columns); map another column to {c!r} as well"
                    )
                if len(header) == 1:
                    hint = " (separate the columns with commas, semicolons or tabs)"
                elif looks:
                    hint = (
                        f"; {looks[0]!r} looks like it: read it with columns={{{c!r}: {looks[0]!r}, ...}} / --columns"
                    )
                    if "deg" in looks[0].lower():
                        hint += " and give its unit: gyr_unit='deg/s' / --gyr-unit deg/s"
                elif c == "t" and header[0] == "":
                    hint = "; the first column has no name: if it holds the times, name it 't'" + _NO_TIME_HINT
                else:
                    hint = (_NO_TIME_HINT if c == "t" else "") + _COLUMNS_READ
                    if not rename:
                        hint += "; a file's own names are read with columns= / --columns, e.g. t=time,gyr_x=GyroX"
                raise ValueError(f"{src}: required column {c!r} missing (header: {file_header}){hint}")
        groups = {}
        for name, cols in CSV_COLUMNS.items():
            present = [c in idx for c in cols]
            if any(present) and not all(present):
                missing = [c for c, p in zip(cols, present) if not p]
                more = " (add them to columns / --columns)" if rename else ""
                raise ValueError(f"{src}: column group {name!r} is incomplete, missing {missing}{more}")
            if all(present):
                groups[name] = cols
            elif name != "t" or (dt is not None and not replace_t):  # t's look-alike is unread when dt times it
                looks = sorted({h for c in cols for h in _lookalikes(c, header)}, key=header.index)
                if looks and name == "t":
                    warnings.warn(
                        f"{src}: column {looks[0]!r} is not read: dt times the log (name the column 't' to use it)",
                        stacklevel=3,
                    )
                elif looks:
                    warnings.warn(
                        f"{src}: columns {looks} are not read: the {name} columns are named {', '.join(cols)}",
                        stacklevel=3,
                    )
        names = [c for cols in groups.values() for c in cols]
        read = [idx[c] for c in names]  # the file's column indices
        body = f.tell()
        table = _read_table_fast(f, read, len(header), sep)
        if table is None:
            f.seek(body)
            table, dated = _read_table_checked(f, header, read, src, sep, first_line=line + 1)
        else:
            dated = False
    at = {c: j for j, c in enumerate(names)}
    data = {}
    for name, cols in groups.items():
        a = table[:, [at[c] for c in cols]]
        data[name] = a[:, 0] if name == "t" else a
    timed_by_dt = "t" not in data
    if timed_by_dt:
        data["t"] = _uniform_times(len(table), dt, src)
    samples, q = check_log(
        ImuSample(data["t"], data["gyr"], data.get("acc"), data.get("mag")), data.get("quat_true"), source=src
    )
    samples = _in_si(samples, src, gyr_unit, acc_unit, time_unit, dated=dated, timed_by_dt=timed_by_dt)
    return (samples, q) if with_truth else samples


def _check_units(gyr_unit: str, acc_unit: str, time_unit: str) -> None:
    for argument, unit in (("gyr_unit", gyr_unit), ("acc_unit", acc_unit), ("time_unit", time_unit)):
        frames.unit_factor(argument, unit)


def _in_si(samples: ImuSample, src: str, gyr_unit, acc_unit, time_unit, *, dated: bool, timed_by_dt: bool):
    """A checked log's gyro, accelerometer and numeric timestamps converted to rad/s, m/s^2 and s."""
    if time_unit != "s" and (dated or timed_by_dt):
        why = "its t column holds date-times, which carry their own unit" if dated else "it is timed by dt (s)"
        raise ValueError(f"{src}: time_unit {time_unit!r} (--time-unit) applies to numeric timestamps, and {why}")
    return samples._replace(
        t=frames.to_si(samples.t, "time_unit", time_unit),
        gyr=frames.to_si(samples.gyr, "gyr_unit", gyr_unit),
        acc=frames.to_si(samples.acc, "acc_unit", acc_unit),
    )


def save_csv(path, samples: ImuSample, quat_true=None) -> None:
    """Write a CSV log with a header (t, gyr_*, then acc_*, mag_*, quat_* where present); NaN as 'nan'."""
    samples, q = check_log(samples, quat_true, source=str(path))
    cols, blocks = list(CSV_COLUMNS["t"]), [samples.t[:, None]]
    for name in ("gyr", "acc", "mag"):
        v = getattr(samples, name)
        if v is not None:
            cols += CSV_COLUMNS[name]
            blocks.append(v)
    if q is not None:
        cols += CSV_COLUMNS["quat_true"]
        blocks.append(q)
    table = np.concatenate(blocks, axis=1)
    io.write_atomic(
        path, lambda f: np.savetxt(f, table, delimiter=",", header=",".join(cols), comments="", fmt="%.17g")
    )


# ------------------------------------------------------------------------------------------------------------
# NPZ
# ------------------------------------------------------------------------------------------------------------
def load_npz(
    path,
    *,
    with_truth: bool = False,
    dt: Optional[float] = None,
    replace_t: bool = False,
    gyr_unit: str = "rad/s",
    acc_unit: str = "m/s^2",
    time_unit: str = "s",
):
    """Read an NPZ log (arrays t, gyr, optional acc, mag, quat_true). Returns ImuSample (or (ImuSample, q)).

    ``dt`` (s): the sample period of a log without a ``t`` array (t = 0, dt, 2 dt, ...); not used when it has one
    (``replace_t``: the array is not read and ``dt`` times the log). Units as in :func:`load_csv`."""
    _check_units(gyr_unit, acc_unit, time_unit)
    src = str(path)
    try:
        z = np.load(path, allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):  # a single .npy array under an .npz name
            raise ValueError("it holds one array, not named arrays t, gyr, ...")
        with z:
            arrays = {k: z[k] for k in z.files if k in ("t", "gyr", "acc", "mag", "quat_true")}
            keys = set(z.files)
    except (ValueError, zipfile.BadZipFile) as e:  # not an NPZ, pickled (object) arrays, a damaged file
        raise ValueError(f"{src}: cannot read it as an NPZ of numeric arrays ({e})") from None
    for k in ("gyr",) if dt is not None else ("t", "gyr"):
        if k not in keys:
            hint = _NO_TIME_HINT if k == "t" else ""
            raise ValueError(f"{src}: required array {k!r} missing (arrays: {sorted(keys)}){hint}")
    if replace_t:
        _uniform_times(0, dt, src)  # dt must be given
        arrays.pop("t", None)
    get = arrays.get
    timed_by_dt = "t" not in arrays
    if timed_by_dt:
        arrays["t"] = _uniform_times(len(np.atleast_1d(arrays["gyr"])), dt, src)
    dated = np.asarray(arrays["t"]).dtype.kind in "Mm"
    samples, q = check_log(ImuSample(get("t"), get("gyr"), get("acc"), get("mag")), get("quat_true"), source=src)
    samples = _in_si(samples, src, gyr_unit, acc_unit, time_unit, dated=dated, timed_by_dt=timed_by_dt)
    return (samples, q) if with_truth else samples


def save_npz(path, samples: ImuSample, quat_true=None) -> None:
    """Write an NPZ log (uncompressed, float64)."""
    samples, q = check_log(samples, quat_true, source=str(path))
    arrays = {"t": samples.t, "gyr": samples.gyr}
    for name in ("acc", "mag"):
        if getattr(samples, name) is not None:
            arrays[name] = getattr(samples, name)
    if q is not None:
        arrays["quat_true"] = q
    io.write_npz(path, arrays)


# ------------------------------------------------------------------------------------------------------------
# By suffix
# ------------------------------------------------------------------------------------------------------------
def _kind(path) -> str:
    suf = Path(path).suffix.lower()
    if suf == ".csv":
        return "csv"
    if suf == ".npz":
        return "npz"
    raise ValueError(f"{path}: unknown log format {suf!r} (use .csv or .npz)")


def load_log(
    path,
    *,
    with_truth: bool = False,
    dt: Optional[float] = None,
    replace_t: bool = False,
    columns: Union[Mapping[str, str], str, None] = None,
    gyr_unit: str = "rad/s",
    acc_unit: str = "m/s^2",
    time_unit: str = "s",
):
    """Read a .csv or .npz log (see the module docstring for columns, units and frames); ``columns``: the CSV
    file's own column names; ``gyr_unit``, ``acc_unit``, ``time_unit``: the file's units (:func:`load_csv`).

    Returns ImuSample(t (N,), gyr (N, 3), acc (N, 3) or None, mag (N, 3) or None) of float64 numpy arrays, or
    (ImuSample, quat_true (N, 4) or None) with ``with_truth=True``. ``dt`` (s): the sample period of a log with
    no timestamps (t = 0, dt, 2 dt, ...; a log's own ``t`` is read instead when it has one, unless
    ``replace_t``: then it is not read at all, for timestamps that are broken). Raises ValueError on wrong
    shapes, missing columns, non-numeric fields, non-finite or non-increasing time.
    """
    kind = _kind(path)
    if columns is not None and kind != "csv":
        raise ValueError(f"log {path}: columns applies to a CSV log, not to an {kind.upper()} file")
    if not Path(path).is_file():
        raise ValueError(f"log {path}: not found" if not Path(path).exists() else f"log {path}: not a file")
    if kind == "csv":
        try:
            with open(path, "rb") as f:
                head = f.read(4096)
        except OSError as e:  # no read permission: one line, as from the loaders below
            raise ValueError(f"log {path}: cannot read it ({e.strerror or e})") from None
        # UTF-16 (with or without its byte-order mark; ASCII in UTF-16 is every other byte NUL, valid UTF-8)
        if head[:2] in (b"\xff\xfe", b"\xfe\xff") or head.count(b"\x00") > len(head) // 4:
            raise ValueError(
                f"log {path}: the text looks like UTF-16 (a byte-order mark or NUL bytes; Excel's 'Unicode Text', "
                "PowerShell's default); save it as UTF-8 (or ASCII) CSV"
            )
    try:
        load = functools.partial(load_csv, columns=columns) if kind == "csv" else load_npz
        return load(
            path,
            with_truth=with_truth,
            dt=dt,
            replace_t=replace_t,
            gyr_unit=gyr_unit,
            acc_unit=acc_unit,
            time_unit=time_unit,
        )
    except UnicodeDecodeError as e:
        if kind != "csv":
            raise ValueError(f"log {path}: cannot read it ({e})") from None
        data = Path(path).read_bytes()  # the position in the file (the decoder's is in its buffer)
        try:
            data.decode("utf-8")
        except UnicodeDecodeError as whole:
            e = whole
        line = data.count(b"\n", 0, e.start) + 1
        raise ValueError(
            f"log {path}: not UTF-8 text, line {line}, byte {e.start} of the file ({e.object[e.start : e.start + 1]!r}"
            "); save it as UTF-8 CSV"
        ) from None
    except (OSError, EOFError) as e:
        raise ValueError(f"log {path}: cannot read it ({e})") from None


def load_trial(
    path,
    *,
    frame: str = "ENU",
    group: str = "own",
    movement=None,
    name: Optional[str] = None,
    dt: Optional[float] = None,
    columns: Union[Mapping[str, str], str, None] = None,
    gyr_unit: str = "rad/s",
    acc_unit: str = "m/s^2",
    time_unit: str = "s",
):
    """A recording with ground truth (a CSV / NPZ log with ``quat_w ... quat_z`` / ``quat_true``) as a
    :class:`jaxatt.data.broad.Trial`, to score and tune on with :func:`jaxatt.broad_score` and :func:`jaxatt.fit`
    like a BROAD trial.

    ``frame``: the navigation frame the truth maps the sensor to ("ENU", "NED", "NWU"), converted to ENU, the
    registered observers' frame on recorded data. North there is the magnetic field's horizontal direction, as
    in BROAD, and the metric fits no offset: truth from a motion-capture system must first be turned from the
    system's own world frame (and the markers' body frame) to that one, or every estimate is off by the yaw
    between them.
    ``movement``: (N,) bool, the samples scored (default: every sample with a finite truth). ``group``: a label
    for the per-group means (BROAD's are "undisturbed" and "disturbed"; a fit weights each group equally, so its
    loss is the mean of the group means, not ``groups["all"]``). ``name``: the trial's name (default the file's
    stem). ``rate_hz`` is 1 / the median step. A log without a magnetometer becomes a 6D trial (mag NaN).
    ``dt`` (s), ``columns`` and the units as in :func:`load_log`.
    """
    from . import broad

    if name is not None and (not isinstance(name, str) or not name.strip()):
        raise ValueError(f"name must be a trial name (text), got {name!r}")
    samples, q = load_log(
        path, with_truth=True, dt=dt, columns=columns, gyr_unit=gyr_unit, acc_unit=acc_unit, time_unit=time_unit
    )
    if q is None:
        raise ValueError(
            f"log {path}: no ground truth (columns quat_w, quat_x, quat_y, quat_z / array quat_true) to score against"
        )
    if samples.acc is None:
        raise ValueError(f"log {path}: no accelerometer columns (acc_x, acc_y, acc_z): a trial needs gyr and acc")
    n = len(samples.t)
    if n < 2:
        raise ValueError(f"log {path}: a trial needs at least 2 samples, got {n}")
    q = frames.change_frame(q, "ENU", frames.check_frame(frame))
    mag = samples.mag if samples.mag is not None else np.full((n, 3), np.nan)
    if movement is None:
        movement = np.all(np.isfinite(q), axis=-1)
    else:
        movement = np.asarray(movement)
        if movement.shape != (n,) or movement.dtype != bool:
            raise ValueError(
                f"movement must be a bool array of shape ({n},), got {movement.dtype}{list(movement.shape)} "
                "(a 0 / 1 array: .astype(bool))"
            )
    if not isinstance(group, str) or not group.strip() or group == "all":
        raise ValueError(f"group must be a label (text, not 'all'), got {group!r}")
    _warn_truth_frame(q, samples.acc, f"log {path}")
    _warn_truth_turns_against_gyro(q, samples.gyr, samples.t, f"log {path}")
    from .. import api  # the front door's units check, as jaxatt.filter makes it (imported when it runs: no cycle)

    t = np.asarray(samples.t, float)
    from_dt = dt is not None and bool(np.allclose(t - t[0], np.arange(n) * float(dt), rtol=1e-9, atol=0.0))
    if dt is not None and not from_dt:  # load_log read the log's own timestamps
        warnings.warn(f"log {path}: dt is not used: the log has timestamps (t, in time_unit)", stacklevel=2)
    api._warn_implausible(
        np.asarray(samples.gyr, float),
        np.asarray(samples.acc, float),
        None if samples.mag is None else np.asarray(samples.mag, float),
        t,
        from_dt=from_dt,
        where=f"log {path}: ",
        api="load_trial",
        cli="jaxatt broad / broad-tune",
    )
    trial = broad.Trial(
        Path(path).stem if name is None else name,
        samples._replace(mag=mag),
        q,
        movement,
        1.0 / float(np.median(np.diff(samples.t))),
        group,
    )
    return broad.check_trials([trial], what=f"log {path}")[0]


def _warn_truth_frame(q_enu: np.ndarray, acc: np.ndarray, where: str, most_deg: float = 45.0) -> None:
    """Warn when the truth's vertical (sensor-to-ENU ``q_enu``'s up, in the sensor frame) is, in the median, more
    than ``most_deg`` from the accelerometer's specific force (which points up at rest): a truth in another frame
    (NED read as ENU is 180 deg off), or a sensor-to-world truth given as world-to-sensor on a tilted sensor (on a
    near-level one :func:`_warn_truth_turns_against_gyro` tells it)."""
    w, x, y, z = (q_enu[:, i] for i in range(4))
    up = np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1)  # R^T e_z
    with np.errstate(invalid="ignore", divide="ignore"):
        a = acc / np.linalg.norm(acc, axis=-1, keepdims=True)
        cos = np.sum(a * up, axis=-1)
    cos = cos[np.isfinite(cos)]
    if cos.size:
        angle = float(np.degrees(np.arccos(np.clip(np.median(cos), -1.0, 1.0))))
        if angle > most_deg:
            warnings.warn(
                f"{where}: the ground truth's vertical is {angle:.0f} deg from the accelerometer's (median): is the "
                "truth's frame right (frame= / --truth-frame ENU, NED or NWU; the truth maps the sensor to it)?",
                stacklevel=3,
            )


def truth_gyro_agreement(q_enu, gyr, t, window_s: float = 0.1, least_deg: float = 3.0) -> Optional[float]:
    """The median cosine between the rotation vector (body frame) of the truth over each window of ``window_s``
    seconds, log(R_k^T R_{k+m}), and the gyro's integral over it, for the windows where both turn more than
    ``least_deg``; None when fewer than 5 do. A truth that maps the sensor to the world turns as the gyro does
    (near 1); one that maps the world to the sensor (its conjugate) turns about the world's axes, backwards (near
    -1 for a sensor turning mostly about the vertical), as a scalar-last truth read as scalar-first mostly does.
    ``q_enu`` (N, 4) (w, x, y, z), ``gyr`` (N, 3) rad/s, ``t`` (N,) s."""
    q, g, t = (np.asarray(x, float) for x in (q_enu, gyr, t))
    n = len(t)
    if n < 3:
        return None
    d = np.diff(t)
    m = max(1, int(round(window_s / float(np.median(d))))) if np.median(d) > 0 else 1
    starts = np.arange(0, n - m, m)[:20000]
    if starts.size < 5:
        return None
    # the gyro's integral over [t_k, t_{k+m}]: sample j+1 covers [t_j, t_{j+1}] (the "next" hold)
    inc = np.concatenate([np.zeros((1, 3)), g[1:] * d[:, None]])
    with np.errstate(invalid="ignore"):
        cum = np.concatenate([np.zeros((1, 3)), np.nancumsum(inc, axis=0)])[1:]
        turn_g = cum[starts + m] - cum[starts]
        q0, q1 = q[starts], q[starts + m]
        w = np.sum(q0 * q1, axis=-1)  # conj(q0) (x) q1: scalar part, then vector part
        v = q0[:, :1] * q1[:, 1:] - q1[:, :1] * q0[:, 1:] - np.cross(q0[:, 1:], q1[:, 1:])
        v = np.where((w < 0)[:, None], -v, v)
        nv = np.linalg.norm(v, axis=-1)
        turn_t = (2.0 * np.arctan2(nv, np.abs(w)) / np.where(nv > 0, nv, 1.0))[:, None] * v
        ng, nt = np.linalg.norm(turn_g, axis=-1), np.linalg.norm(turn_t, axis=-1)
        least = np.radians(least_deg)
        ok = np.isfinite(ng) & np.isfinite(nt) & (ng > least) & (nt > least) & (nt < np.radians(150.0))
        if ok.sum() < 5:
            return None
        cos = np.sum(turn_g[ok] * turn_t[ok], axis=-1) / (ng[ok] * nt[ok])
    return float(np.median(cos))


def _warn_truth_turns_against_gyro(q_enu, gyr, t, where: str) -> None:
    """Warn when the truth does not turn as the gyro does (:func:`truth_gyro_agreement` below 0.5, 60 deg; the
    20 BROAD trials read 0.999-1.0, their conjugates -0.12 to -0.996)."""
    c = truth_gyro_agreement(q_enu, gyr, t)
    if c is None:  # a slow recording: longer windows
        c = truth_gyro_agreement(q_enu, gyr, t, window_s=0.5)
    if c is not None and c < 0.5:
        warnings.warn(
            f"{where}: the ground truth does not turn as the gyro does (median cosine {c:.2f} between their "
            "rotations over short windows, 1 when they agree): does the truth map the world to the sensor (give its "
            "conjugate), is it scalar-last (jaxatt reads w, x, y, z), is its body frame not the IMU's, or is it "
            "offset in time from the IMU?",
            stacklevel=3,
        )


def save_log(path, samples: ImuSample, quat_true=None) -> None:
    """Write a .csv or .npz log (format from the suffix); validates like :func:`load_log`."""
    (save_csv if _kind(path) == "csv" else save_npz)(path, samples, quat_true)

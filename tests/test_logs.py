"""Plain IMU logs: CSV / NPZ round trips and clear errors on bad input."""

import numpy as np
import pytest

from jaxatt.data import logs
from jaxatt.types import ImuSample


def make_log(n=50, seed=0, with_acc=True, with_mag=True):
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.001, 0.02, n)) + 1e3 / 3
    gyr = rng.normal(size=(n, 3))
    acc = rng.normal(size=(n, 3)) * 9.81 if with_acc else None
    mag = rng.normal(size=(n, 3)) * 48.123456789 if with_mag else None
    gyr[3, 1] = np.nan
    if with_acc:
        acc[7] = np.nan
    if with_mag:
        mag[11, 2] = np.nan
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[5] = np.nan
    return ImuSample(t, gyr, acc, mag), q


def assert_same(a: ImuSample, b: ImuSample):
    for name in ("t", "gyr", "acc", "mag"):
        x, y = getattr(a, name), getattr(b, name)
        if x is None:
            assert y is None, name
        else:
            np.testing.assert_array_equal(x, y, err_msg=name)  # NaN == NaN here; exact equality otherwise


@pytest.mark.parametrize("suffix", [".csv", ".npz"])
@pytest.mark.parametrize("sensors", [(True, True), (True, False), (False, False)])
def test_round_trip(tmp_path, suffix, sensors):
    s, q = make_log(with_acc=sensors[0], with_mag=sensors[1])
    p = tmp_path / f"log{suffix}"
    logs.save_log(p, s, q)
    back, q_back = logs.load_log(p, with_truth=True)
    assert_same(s, back)
    np.testing.assert_array_equal(q, q_back)
    assert back.gyr.dtype == np.float64 and isinstance(back.t, np.ndarray)
    assert_same(s, logs.load_log(p))  # without truth: just the samples
    logs.save_log(p, s)
    assert logs.load_log(p, with_truth=True)[1] is None


def test_csv_column_order_extras_and_empty_fields(tmp_path):
    p = tmp_path / "x.csv"
    p.write_text(
        "note,mag_z,mag_y,mag_x,t,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z\n"
        "a,3,2,1,0.0,0.1,0.2,0.3,0,0,9.8\n"
        "b,6,5,4,0.01,,0.5,0.6,nan,0,9.8\n"
        "\n"
    )
    s = logs.load_log(p)
    np.testing.assert_array_equal(s.t, [0.0, 0.01])
    np.testing.assert_array_equal(s.mag, [[1, 2, 3], [4, 5, 6]])
    assert np.isnan(s.gyr[1, 0]) and s.gyr[1, 1] == 0.5
    assert np.isnan(s.acc[1, 0])


def test_csv_errors(tmp_path):
    def bad(text, match):
        p = tmp_path / "bad.csv"
        p.write_text(text)
        with pytest.raises(ValueError, match=match):
            logs.load_log(p)

    bad("", "header")
    bad("0.0,1,2,3\n0.1,1,2,3\n", "header")
    bad("t,gyr_x,gyr_y\n0,1,2\n", "gyr_z")
    bad("t,gyr_x,gyr_y,gyr_z,acc_x,acc_y\n0,1,2,3,4,5\n", "incomplete")
    bad("t,gyr_x,gyr_y,gyr_z\n", "no data")
    bad("t,gyr_x,gyr_y,gyr_z\n0,1,2,abc\n", "not a number")
    bad("t,gyr_x,gyr_y,gyr_z\n0,1,2\n", "fields")
    bad("t,gyr_x,gyr_y,gyr_z\n0.1,1,2,3\n0.1,1,2,3\n", "strictly increasing")
    bad("t,gyr_x,gyr_y,gyr_z\n0.2,1,2,3\n0.1,1,2,3\n", "strictly increasing")
    bad("t,gyr_x,gyr_y,gyr_z\nnan,1,2,3\n0.1,1,2,3\n", "finite")
    bad("t,gyr_x,gyr_y,gyr_z\n0,1,2,inf\n", "inf")
    bad("t,t,gyr_x,gyr_y,gyr_z\n0,0,1,2,3\n", "duplicate")


def test_csv_as_loggers_and_spreadsheets_write_it(tmp_path):
    """Comment lines above the header are skipped and R's NA / N/A / null cells are missing readings (the file
    reads as the plain one); a column named nearly as one of the format's is named in the error or a warning
    with the name to give it, a nameless first column (a pandas index) is said to be one."""
    p = tmp_path / "x.csv"
    plain = "t,gyr_x,gyr_y,gyr_z,mag_x,mag_y,mag_z\n0,1,2,3,4,5,nan\n0.1,1,nan,3,nan,5,6\n"
    p.write_text(plain)
    want = logs.load_log(p)
    p.write_text(
        "# logger v1\n# device: phone\n" + plain.replace(",nan,3,nan,", ",NA,3,null,").replace("5,nan", "5,N/A")
    )
    assert_same(want, logs.load_log(p))

    def said(header, match):
        p.write_text(header + "\n" + ",".join(["0.5"] * (header.count(",") + 1)) + "\n")
        with pytest.raises(ValueError, match=match):
            logs.load_log(p)

    said(
        "time,gyr_x,gyr_y,gyr_z",
        r"column 't' missing .*; 'time' looks like it: read it with columns=\{'t': 'time', \.\.\.\} / --columns$",
    )
    said("T,GYR_X,GYR_Y,GYR_Z", r"'T' looks like it: read it with columns=\{'t': 'T'")
    said("t [s],gyr_x [rad/s],gyr_y [rad/s],gyr_z [rad/s]", r"'t \[s\]' looks like it: read it with columns=")
    said("t,gyr_x [deg/s],gyr_y [deg/s],gyr_z [deg/s]", r"/ --columns and give its unit: gyr_unit='deg/s' / --gyr-unit")
    said("t,gyro_x,gyro_y,gyro_z", r"column 'gyr_x' missing .*'gyro_x' looks like it: read it with columns=\{'gyr_x'")
    said(
        "t,gx,gy,gz",
        r"'gyr_x' missing .*; the columns read are t, gyr_x, .*; a file's own names are read with columns=",
    )
    said(",gyr_x,gyr_y,gyr_z", r"the first column has no name: if it holds the times, name it 't'")
    p.write_text("t,gyr_x,gyr_y,gyr_z,magn_x,magn_y,magn_z\n0,1,2,3,4,5,6\n")
    with pytest.warns(UserWarning, match=r"columns \['magn_x', 'magn_y', 'magn_z'\] are not read: the mag columns are"):
        assert logs.load_log(p).mag is None


def test_npz_errors(tmp_path):
    p = tmp_path / "bad.npz"
    np.savez(p, t=np.arange(3.0), gyr=np.zeros((3, 2)))
    with pytest.raises(ValueError, match=r"gyr must have shape \(N, 3\)"):
        logs.load_log(p)
    np.savez(p, t=np.arange(3.0))
    with pytest.raises(ValueError, match="'gyr' missing"):
        logs.load_log(p)
    np.savez(p, t=np.arange(3.0), gyr=np.zeros((4, 3)))
    with pytest.raises(ValueError, match="rows"):
        logs.load_log(p)
    np.savez(p, t=np.array([0.0, 2.0, 1.0]), gyr=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="strictly increasing"):
        logs.load_log(p)
    np.savez(p, t=np.arange(3.0), gyr=np.zeros((3, 3)), quat_true=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="quat_true"):
        logs.load_log(p, with_truth=True)
    np.savez(p, t=np.arange(3.0), gyr=np.zeros((3, 3)), quat_true=np.tile([0.0, 0.0, 0.0, 3.0], (3, 1)))
    with pytest.raises(
        ValueError, match=r"quat_true \(CSV columns quat_w \.\.\. quat_z\) row 0 has norm 3.*: normalise each row"
    ):
        logs.load_log(p, with_truth=True)
    # files numpy reads but that are not logs of real numbers: each error names the file
    np.savez(p, t=np.array([object()] * 3, dtype=object), gyr=np.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"bad\.npz: cannot read it as an NPZ of numeric arrays"):
        logs.load_log(p)
    np.savez(p, t=np.arange(3.0), gyr=np.zeros((3, 3)) + 1j)
    with pytest.raises(ValueError, match=r"bad\.npz: gyr is complex"):
        logs.load_log(p)
    with open(p, "wb") as f:
        np.save(f, np.arange(3.0))  # one .npy array under an .npz name
    with pytest.raises(ValueError, match=r"bad\.npz: .*one array"):
        logs.load_log(p)
    p.write_text("not a zip")
    with pytest.raises(ValueError, match=r"bad\.npz: cannot read it"):
        logs.load_log(p)


def test_a_utf16_or_latin1_csv_is_named_as_such(tmp_path):
    """Excel's "Unicode Text" and PowerShell write UTF-16: the error says so and how to save it, instead of a
    codec message; other non-UTF-8 bytes are named with their position."""
    text = "t,gyr_x,gyr_y,gyr_z\n0,0,0,0\n0.01,0,0,0\n"
    for enc in ("utf-16", "utf-16-le"):
        p = tmp_path / f"{enc}.csv"
        p.write_bytes(text.encode(enc))
        with pytest.raises(ValueError, match=rf"{enc}\.csv: the text looks like UTF-16 .*save it as UTF-8"):
            logs.load_log(p)
    p = tmp_path / "latin.csv"
    p.write_bytes("t,gyr_x,gyr_y,gyr_z\n0,0,0,0 # 1\u00b0/s\n".encode("latin-1"))
    with pytest.raises(ValueError, match=r"latin\.csv: not UTF-8 text, line 2, byte 31 of the file \(b'\\xb0'\)"):
        logs.load_log(p)


def test_csv_rows_with_more_fields_than_the_header_and_a_byte_order_mark(tmp_path):
    """One extra field on a row shifted its values one column (gyr_y = 999) silently; now it names the line. A
    byte-order mark (Excel's "CSV UTF-8") is skipped, not read into the first column's name."""
    n = 6
    samples = ImuSample(np.arange(n) * 0.01, np.zeros((n, 3)), np.tile([0, 0, 9.81], (n, 1)), None)
    good = tmp_path / "good.csv"
    logs.save_log(good, samples)
    lines = good.read_text().splitlines()
    row = lines[3].split(",")
    lines[3] = ",".join(row[:2] + ["999"] + row[2:])
    bad = tmp_path / "extra.csv"
    bad.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"extra\.csv: line 4 has 8 fields, header has 7"):
        logs.load_log(bad)
    bom = tmp_path / "bom.csv"
    bom.write_bytes(b"\xef\xbb\xbf" + good.read_bytes())
    np.testing.assert_array_equal(logs.load_log(bom).gyr, logs.load_log(good).gyr)


def test_save_validates_and_suffix(tmp_path):
    s, _ = make_log()
    with pytest.raises(ValueError, match=r"acc must have shape"):
        logs.save_log(tmp_path / "a.csv", s._replace(acc=s.acc[:, :2]))
    with pytest.raises(ValueError, match="rows"):
        logs.save_log(tmp_path / "a.npz", s._replace(mag=s.mag[:-1]))
    with pytest.raises(ValueError, match="strictly increasing"):
        logs.save_log(tmp_path / "a.npz", s._replace(t=s.t[::-1]))
    with pytest.raises(ValueError, match="unknown log format"):
        logs.save_log(tmp_path / "a.txt", s)
    with pytest.raises(ValueError, match="unknown log format"):
        logs.load_log(tmp_path / "a.h5")
    # NPZ with another suffix spelling keeps its name (np.savez appends .npz to names it does not recognise)
    logs.save_log(tmp_path / "UPPER.NPZ", s)
    assert (tmp_path / "UPPER.NPZ").exists()
    assert_same(s, logs.load_log(tmp_path / "UPPER.NPZ"))


@pytest.mark.parametrize("sep, decimal", [(";", "."), (";", ","), ("\t", "."), ("\t", ",")])
def test_csv_separated_by_semicolons_or_tabs_reads_as_the_comma_file(tmp_path, sep, decimal):
    """Spreadsheets in many locales write ';' (or tabs) between fields and a decimal comma: the same log, written
    that way, reads back bit for bit (the separator is the header's; missing cells stay NaN)."""
    s, _ = make_log()
    p = tmp_path / "x.csv"
    logs.save_csv(p, s)
    text = p.read_text()
    other = tmp_path / "y.csv"
    other.write_text(text.replace(",", sep).replace(".", decimal))
    assert_same(s, logs.load_csv(other))
    spaced = tmp_path / "z.csv"
    spaced.write_text(text.replace(",", " "))
    with pytest.raises(ValueError, match=r"required column 't' missing .*separate the columns with commas, semicolons"):
        logs.load_csv(spaced)


@pytest.mark.parametrize("suffix", [".csv", ".npz"])
def test_a_log_without_timestamps_is_timed_by_dt(tmp_path, suffix):
    """Fixed-rate loggers often write no time: with dt the log reads as t = 0, dt, 2 dt, ...; without it the
    missing t is named with the way out; a log that has t keeps it (dt is the caller's to apply)."""
    s, q = make_log()
    p = tmp_path / f"x{suffix}"
    logs.save_log(p, s, q)
    if suffix == ".csv":
        p.write_text("\n".join(line.split(",", 1)[1] for line in p.read_text().splitlines()) + "\n")
    else:
        with np.load(p) as z:
            arrays = {k: z[k] for k in z.files if k != "t"}
        np.savez(p, **arrays)
    back, q_back = logs.load_log(p, with_truth=True, dt=0.005)
    np.testing.assert_array_equal(back.t, np.arange(len(s.t)) * 0.005)
    assert_same(s._replace(t=back.t), back)
    np.testing.assert_array_equal(q_back, q)
    with pytest.raises(ValueError, match=r"required (column|array) 't' missing .*give the sample period"):
        logs.load_log(p)
    for bad in (0.0, -1.0, float("nan"), "x", "0.005", True):  # True is not 1 s, "0.005" is text
        with pytest.raises(ValueError, match="dt must be a"):
            logs.load_log(p, dt=bad)
    logs.save_log(p, s)
    assert_same(s, logs.load_log(p, dt=0.005))
    # replace_t: the log's own t is not read (it may be broken) and dt times the log
    assert_same(s._replace(t=back.t), logs.load_log(p, dt=0.005, replace_t=True))
    with pytest.raises(ValueError, match="dt must be a number of seconds, got None"):
        logs.load_log(p, replace_t=True)


def test_csv_fast_reader_equals_the_checked_reader(tmp_path):
    """numpy's C reader (plain numeric files) and the cell-by-cell reader (the fallback) give the same table,
    and a file the fast reader refuses (an empty cell) still loads through the fallback."""
    rng = np.random.default_rng(3)
    n = 500
    s = ImuSample(np.arange(n) * 0.01, rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), rng.normal(size=(n, 3)))
    p = tmp_path / "x.csv"
    logs.save_csv(p, s)
    fast = logs.load_csv(p)
    with open(p, newline="") as f:
        header = f.readline().strip().split(",")
        checked, dated = logs._read_table_checked(f, header, list(range(len(header))), str(p))
    assert not dated
    np.testing.assert_array_equal(fast.t, checked[:, 0])
    np.testing.assert_array_equal(fast.gyr, checked[:, 1:4])
    np.testing.assert_array_equal(fast.mag, checked[:, 7:10])
    with open(p, newline="") as f:
        f.readline()
        assert logs._read_table_fast(f, list(range(len(header))), len(header)) is not None
    lines = p.read_text().splitlines()
    lines[5] = lines[5].replace(lines[5].split(",")[2], "", 1)  # an empty gyr_y cell on line 6
    p.write_text("\n".join(lines) + "\n")
    got = logs.load_csv(p)
    assert np.isnan(got.gyr[4, 1]) and np.isfinite(np.delete(got.gyr, 4, axis=0)).all()


_MS = np.array([0, 1, 2, 4], "timedelta64[ms]")  # 1 ms steps (one 2 ms gap)


def test_datetime_and_timedelta_timestamps_become_seconds(tmp_path):
    """datetime64 / timedelta64 timestamps were read as plain numbers of their unit: 1 ms steps became 1 s (and
    passed the "are the timestamps in ms?" check of jaxatt.filter). Now seconds, from each array's own unit; dates
    count from the first sample."""
    gyr = np.zeros((4, 3))
    want = [0.0, 0.001, 0.002, 0.004]
    start = np.datetime64("2024-05-01T12:00:00", "ms")
    cases = {
        "datetime64[ms]": start + _MS,
        "datetime64[ns]": (start + _MS).astype("datetime64[ns]"),
        "timedelta64[us]": _MS.astype("timedelta64[us]"),
    }
    for name, t in cases.items():
        s, _ = logs.check_log(ImuSample(t, gyr))  # arrays (a pandas column reads as datetime64[ns])
        np.testing.assert_allclose(s.t, want, rtol=0, atol=1e-15, err_msg=name)
        assert s.t.dtype == np.float64
        p = tmp_path / "dt.npz"
        np.savez(p, t=t, gyr=gyr)  # an NPZ of datetime64 / timedelta64
        np.testing.assert_allclose(logs.load_log(p).t, want, rtol=0, atol=1e-15, err_msg=name)
    # a timedelta keeps its own origin (elapsed time), it is not re-based on the first sample
    np.testing.assert_allclose(logs.check_log(ImuSample(_MS + np.timedelta64(5, "s"), gyr))[0].t, np.add(want, 5.0))
    # CSV: ISO 8601 date-times in t (as pandas writes a datetime column), a UTC offset included
    p = tmp_path / "dt.csv"
    p.write_text(
        "t,gyr_x,gyr_y,gyr_z\n"
        "2024-05-01 12:00:00.000000,0,0,0\n2024-05-01 12:00:00.001000,0,0,0\n"
        "2024-05-01T12:00:00.002+00:00,0,0,0\n2024-05-01 12:00:00.004,0,0,0\n"
    )
    np.testing.assert_allclose(logs.load_log(p).t, want, rtol=0, atol=1e-15)
    p.write_text("t,gyr_x,gyr_y,gyr_z\n2024-05-01 12:00:00,0,0,0\n0.5,0,0,0\n")
    with pytest.raises(ValueError, match=r"dt\.csv: line 3: column 't': '0\.5' is not a date-time like the first"):
        logs.load_log(p)


@pytest.mark.parametrize(
    "field,value,match",
    [
        ("t", np.array(["0.0", "0.1", "0.2", "0.3"]), r"t is not numeric: dtype <U3, expected real numbers"),
        ("t", np.array([0.0, 0.1, 0.2, 0.3], dtype=object), r"t is not numeric: dtype object"),
        ("t", np.array([1, 2, 3, 4], "datetime64[M]"), r"t is not numeric: datetime64\[M\] has no fixed length"),
        ("t", np.array(["2024-01-01", "NaT", "2024-01-03", "2024-01-04"], "datetime64[ns]"), r"t must be finite"),
        ("gyr", np.zeros((4, 3)).astype(str), r"gyr is not numeric: dtype <U32"),
        ("acc", np.zeros((4, 3), "timedelta64[s]"), r"acc is not numeric: dtype timedelta64\[s\]"),
        ("mag", np.zeros((4, 3), bool), r"mag is not numeric: dtype bool"),
    ],
)
def test_non_numeric_fields_are_refused_in_one_line(tmp_path, field, value, match):
    s = ImuSample(np.arange(4) * 0.01, np.zeros((4, 3)))._replace(**{field: value})
    with pytest.raises(ValueError, match=match):
        logs.check_log(s)
    with pytest.raises(ValueError, match=match):
        logs.save_log(tmp_path / "x.npz", s)
    if value.dtype.kind != "O":  # an NPZ cannot hold objects without pickle (its own error, tested above)
        p = tmp_path / "y.npz"
        np.savez(p, **{"t": np.arange(4) * 0.01, "gyr": np.zeros((4, 3)), field: value})
        with pytest.raises(ValueError, match=match):
            logs.load_log(p)


def test_csv_errors_name_the_file_line_and_numpy_savetxt_headers_read(tmp_path):
    """Error lines count every line of the file (comments and blank lines above the header and between rows);
    a quote left open is named (in a long file Python's csv reader stopped with 'field larger than field limit',
    a traceback); blank lines above the header are skipped and numpy.savetxt's commented header
    ('# t,gyr_x,...', its default) is the header: the file reads as the plain one (numpy writes both)."""
    p = tmp_path / "x.csv"

    def bad(text, match):
        p.write_text(text)
        with pytest.raises(ValueError, match=match):
            logs.load_log(p)

    bad("# logger\n\nt,gyr_x,gyr_y,gyr_z\n0,1,2,3\n\n0.1,1,x,3\n", r"x\.csv: line 6: column 'gyr_y': 'x' is not")
    bad('t,gyr_x,gyr_y,gyr_z\n0,1,2,3\n0.1,"1,2,3\n0.2,1,2,3\n', r"line 3 has 2 fields.*a quote \(\"\) opened there")
    rows = [f"{0.01 * i:.2f},1,2,3" for i in range(30000)]
    rows[40] = '0.40,"1,2,3'
    bad("t,gyr_x,gyr_y,gyr_z\n" + "\n".join(rows) + "\n", r"line 42: cannot be read as CSV .*a quote \(\"\) left open")
    bad("# notes\n0,1,2,3\n", r"line 2 must be a header naming the columns")
    table = np.array([[0.0, 1.0, 2.0, 3.0], [0.01, 1.5, 2.5, 3.5]])
    np.savetxt(p, table, delimiter=",", header="t,gyr_x,gyr_y,gyr_z", comments="")
    want = logs.load_log(p)
    np.savetxt(p, table, delimiter=",", header="t,gyr_x,gyr_y,gyr_z")  # '# t,gyr_x,...'
    assert_same(want, logs.load_log(p))
    p.write_text("\n\n" + p.read_text())
    assert_same(want, logs.load_log(p))


def test_a_logger_s_own_column_names_read_through_columns(tmp_path):
    """A CSV with a logger's names (time, GyroX, ..., AccX, ...), read with ``columns``, gives the same samples
    as the file written with the format's names; a column that carries a format's name but is mapped from
    another is not read; the mapping given as text (the CLI's --columns) is the same mapping."""
    s, _ = make_log(with_mag=False)
    ours = tmp_path / "ours.csv"
    logs.save_log(ours, s)
    theirs = tmp_path / "theirs.csv"
    names = {"t": "time", "gyr_x": "GyroX", "gyr_y": "GyroY", "gyr_z": "GyroZ"}
    names.update({"acc_x": "AccX", "acc_y": "AccY", "acc_z": "acc_x"})  # the file's acc_x holds the format's acc_z
    lines = ours.read_text().splitlines()
    header = lines[0].split(",")
    theirs.write_text("\n".join([",".join(names.get(h, h) for h in header)] + lines[1:]) + "\n")
    with pytest.raises(ValueError, match="required column 't' missing"):
        logs.load_log(theirs)
    assert_same(s, logs.load_log(theirs, columns=names))
    assert_same(s, logs.load_csv(theirs, columns=",".join(f"{k}={v}" for k, v in names.items())))


@pytest.mark.parametrize(
    "columns, match",
    [
        ({"gyro_x": "GyroX"}, r"columns: 'gyro_x' is not one of the format's columns \(t, gyr_x, "),
        ({"gyr_x": "a", "gyr_y": "a"}, r"columns: the file's column 'a' is given for more than one"),
        ({"gyr_x": ""}, r"columns: the file's column for 'gyr_x' must be a name, got ''"),
        ("gyr_x:GyroX", r"columns must be 'name=column,...' \(e.g. 'gyr_x=GyroX,t=time'\), got 'gyr_x:GyroX'"),
        (["gyr_x"], r"columns must be a mapping of the format's column names to the file's"),
        ({"gyr_x": "GyroQ"}, r"x.csv: column 'GyroQ' \(given in columns\) is not in the header: \['t', 'gyr_x'"),
        ("gyr_x=a,gyr_x=b", r"columns: 'gyr_x' is given more than once"),
        ("gyr_x=gyr_y", r"required column 'gyr_y' missing: the file's column 'gyr_y' is read as 'gyr_x' \(columns\)"),
        (
            {"GyroX": "gyr_x"},
            r"'GyroX' is not one of .* \(the names on the left are jaxatt's, on the right the file's\)",
        ),
    ],
)
def test_bad_columns_are_one_line_naming_the_entry(tmp_path, columns, match):
    p = tmp_path / "x.csv"
    logs.save_log(p, make_log(with_acc=False, with_mag=False)[0])
    with pytest.raises(ValueError, match=match) as e:
        logs.load_log(p, columns=columns)
    assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match=r"columns applies to a CSV log, not to an NPZ file"):
        logs.load_log(tmp_path / "x.npz", columns={"gyr_x": "g"})


def test_an_incomplete_mapping_is_said_with_the_file_s_own_header(tmp_path):
    p = tmp_path / "x.csv"
    p.write_text("time,GyroX,GyroY,GyroZ,AccX,AccY,AccZ\n0,1,2,3,4,5,6\n0.01,1,2,3,4,5,6\n")
    cols = {"t": "time", "gyr_x": "GyroX", "gyr_y": "GyroY", "gyr_z": "GyroZ"}
    with pytest.raises(ValueError, match=r"group 'acc' is incomplete, missing \['acc_y', 'acc_z'\] \(add them to col"):
        logs.load_log(p, columns={**cols, "acc_x": "AccX"})
    with pytest.raises(ValueError, match=r"'gyr_z' missing \(header: \['time', 'GyroX', 'GyroY', 'GyroZ', 'AccX'"):
        logs.load_log(p, columns={"t": "time", "gyr_x": "GyroX", "gyr_y": "GyroY"})


def test_a_log_in_a_logger_s_units_reads_as_the_same_log_in_si_units(tmp_path):
    """gyr_unit / acc_unit / time_unit of load_log (CSV, with quoted names after ", ", and NPZ) give the log
    written in rad/s, m/s^2 and s; date-time stamps carry their own unit and a log timed by dt has no t column,
    so time_unit is refused for them in one line."""
    s, _ = make_log(with_mag=False)
    units = {"gyr_unit": "mdps", "acc_unit": "mg", "time_unit": "us"}
    raw = s._replace(t=s.t * 1e6, gyr=np.rad2deg(s.gyr) * 1e3, acc=s.acc / 9.80665 * 1e3)
    p = tmp_path / "raw.csv"
    logs.save_log(p, raw)
    lines = p.read_text().splitlines()
    quoted = ", ".join(f'"{h} (logger)"' for h in lines[0].split(","))  # "t (logger)", "gyr_x (logger)", ...
    p.write_text("\n".join([quoted] + lines[1:]) + "\n")
    cols = {h: f"{h} (logger)" for h in lines[0].split(",")}
    back = logs.load_log(p, columns=cols, **units)
    for name in ("t", "gyr", "acc"):
        np.testing.assert_allclose(getattr(back, name), getattr(s, name), rtol=1e-13, err_msg=name)
    logs.save_log(tmp_path / "raw.npz", raw)
    back = logs.load_log(tmp_path / "raw.npz", **units)
    for name in ("t", "gyr", "acc"):
        np.testing.assert_allclose(getattr(back, name), getattr(s, name), rtol=1e-13, err_msg=name)
    dated = tmp_path / "dated.csv"
    dated.write_text("t,gyr_x,gyr_y,gyr_z\n2024-05-01 12:00:00.000,0,0,0\n2024-05-01 12:00:00.010,0,0,0\n")
    np.testing.assert_allclose(logs.load_log(dated).t, [0.0, 0.01])
    with pytest.raises(
        ValueError, match=r"dated.csv: time_unit 'ms' \(--time-unit\) applies to numeric .* date-times, which carry"
    ):
        logs.load_log(dated, time_unit="ms")
    np.savez(
        tmp_path / "dated.npz",
        t=np.array(["2024-05-01T12:00", "2024-05-01T12:01"], "datetime64[ms]"),
        gyr=np.zeros((2, 3)),
    )
    with pytest.raises(ValueError, match=r"dated.npz: time_unit 'ms' \(--time-unit\) applies to numeric .* date-times"):
        logs.load_log(tmp_path / "dated.npz", time_unit="ms")
    with pytest.raises(
        ValueError, match=r"time_unit 'ms' \(--time-unit\) applies to numeric timestamps, and it is timed by dt \(s\)"
    ):
        logs.load_log(p, columns=cols, dt=0.01, replace_t=True, time_unit="ms")
    with pytest.raises(ValueError, match=r"gyr_unit must be one of 'rad/s', 'deg/s', 'dps', 'mdps', got 'rpm'"):
        logs.load_log(p, gyr_unit="rpm")

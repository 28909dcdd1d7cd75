"""The observer registry: one place that names every built-in observer.

Each observer module declares its :class:`Entry` (or several, one per variant) in a module-level ``ENTRIES``
tuple: its name, factory, default params, tunable gains (units, constraint, tuned by default or not) and how it
sets itself up on recorded data (initial attitude from the first samples, reference vectors, the navigation frame
of its estimate). :data:`INDEX` maps each name to its module, so the names (CLI choices, docs) are known without
importing JAX; :func:`get` imports the module on first use. The front door (:func:`jaxatt.filter`,
:func:`jaxatt.broad_score`, :func:`jaxatt.fit`), the BROAD runner, the fitter and the CLI all read from here.

Adding an observer: write its module (``Params``, ``State``, ``Out``, ``make_observer``, ``ENTRIES``), add a line
to :data:`INDEX`, a test and a docs page.

Frames and units on recorded data (what ``setup`` and ``default_params`` assume): body-frame gyro in rad/s,
accelerometer in m/s^2 (specific force, "up" at rest), magnetometer in any unit (its own first sample is the
reference); the estimate maps sensor to ``Entry.frame`` (ENU for every built-in), :func:`jaxatt.filter` converts
it to the frame asked for.
"""

from __future__ import annotations

import importlib
from typing import Any, Callable, Dict, NamedTuple, Optional, Tuple, Union

import jax.numpy as jnp

from .. import so3
from ..types import Observer

__all__ = [
    "Gain",
    "Entry",
    "INDEX",
    "names",
    "get",
    "register",
    "builtin",
    "check_entry",
    "recorded_observer",
    "hold_of",
    "with_hold",
    "CONSTRAINTS",
    "first_sample_frame",
    "markdown_table",
]

#: Constraints a gain can declare (the fitter maps each to a transform, :mod:`jaxatt.fitting.parametrize`):
#: "positive" (elementwise > 0, learnt in log space), "schedule" (a positive piecewise-constant gain, one value per
#: interval of the params' ``switch_times``), "spd" (symmetric positive definite, scaled Cholesky factor),
#: "spd-diagonal" (SPD kept diagonal), "real" (unconstrained).
CONSTRAINTS = ("positive", "schedule", "spd", "spd-diagonal", "real")


class Gain(NamedTuple):
    """One tunable field of an observer's Params.

    Fields:
        field: the Params field.
        unit: its unit (as in the Params; e.g. "1/s", "s", "rad/s").
        doc: one line on what it does (with the paper's equation where there is one).
        constraint: one of :data:`CONSTRAINTS`.
        tuned: tuned by default (``jaxatt.fit`` without ``tune=``).
        bounds: optional (low, high) for "positive" gains: the fitter keeps the gain inside (a prior on sensible
            values; e.g. time constants between 0.05 s and 30 s).
        rate: optional (label, fn(params) -> factor): ``value * factor`` is also written in gains files (e.g. the
            gain as a rate in 1/s when its own unit is 1/(s nT^2)).
        scale: optional, for "real" gains: the fitter learns value / scale (one unit of it is a sensible step;
            e.g. 0.01 for a delay in seconds).
    """

    field: str
    unit: str
    doc: str
    constraint: str = "positive"
    tuned: bool = True
    bounds: Optional[Tuple[float, float]] = None
    rate: Optional[Tuple[str, Callable[[Any], Any]]] = None
    scale: Optional[float] = None


class Entry(NamedTuple):
    """A registered observer.

    Fields:
        name: registry name (CLI ``--observer``, ``jaxatt.filter(name, ...)``).
        summary: one line (docs table, ``--help``).
        reference: paper and equations.
        make: ``make() -> Observer`` (the default variant; cached by the module).
        default_params: ``default_params(dtype) -> Params``: the gains used when none are given (for observers
            with ``setup``: in recorded-data units, rad/s, m/s^2, the data's magnetometer unit).
        gains: the tunable gains (:class:`Gain`).
        setup: ``setup(params, first_sample) -> params`` filling the per-recording fields (initial attitude,
            reference vectors) from the first sample, differentiable in the gains; None when ``init`` needs
            nothing more. ``recorded`` False: the observer is not set up for recorded data (its params must be
            given, in the frame and units of its paper).
        setup_fields: the Params fields ``setup`` fills.
        frame: navigation frame of ``Out.q`` / ``Out.r`` after ``setup`` ("ENU", "NED", "NWU").
        hold: the input of a step (:data:`jaxatt.types.HOLDS`): "next" for filters that update with each new
            sample (ahrs, VQF, BROAD), "zoh" / "linear" for continuous-time observers. None (the default): the
            observer's own (``make().hold``), else "next" (:func:`hold_of`). jaxatt's observers declare it on the
            Observer, so a runner given the Observer alone (:func:`jaxatt.montecarlo.run`) uses the same.
        needs: the ImuSample fields it needs besides gyr.
        shipped: a gains file of :mod:`jaxatt.data.gains` used instead of ``default_params`` when no params are
            given (e.g. the robust AHRS tuned on BROAD), or None.
        module: the module that declares it (docs page: docs/observers/<module>.md).
        check: optional ``check(params)`` raising ValueError with a clear message.
        recorded: False for an observer not set up for recorded data.
        init_reads: the sensors whose first reading ``init`` starts from (its attitude, its references) without a
            ``setup``: on recorded data a missing reading in row 0 of them is replaced by that sensor's first
            present one (:func:`jaxatt.api.start_from_valid`), as for an observer with ``setup``.
        first_step: the Params field holding the sampling time (s) of ``init``'s update with the first sample (VQF's
            ``ts0``), or "": :func:`jaxatt.filter`, :func:`jaxatt.broad_score` and :func:`jaxatt.fit` set it to the
            recording's first step (the median over trials) unless the params given name it
            (:func:`jaxatt.api.recording_defaults`, as for ``field_unit_gains``).
        field_unit_gains: gains in the magnetometer's unit squared (noise covariances). When they come from the
            defaults, :func:`jaxatt.filter`, :func:`jaxatt.broad_score` and :func:`jaxatt.fit` (its start) scale
            them by (|m| / |m_ref|)^2: |m| the recording's first field reading (the median over trials), |m_ref|
            that of the defaults' ``mag_ref_nav``. The defaults then mean the same in uT, nT or gauss.
        advise: optional ``advise(params, outputs, samples) -> str or None``: after :func:`jaxatt.filter` ran it
            over a recording (``outputs``: its output fields, ``samples``: the recording's ImuSample as it ran, gyr
            and acc in SI units, mag in the recording's unit; numpy arrays), a warning worth giving about that run
            (e.g. the robust AHRS's magnetic gate shut in most samples), or None.
    """

    name: str
    summary: str
    reference: str
    make: Callable[[], Observer]
    default_params: Callable[..., Any]
    gains: Tuple[Gain, ...]
    setup: Optional[Callable[[Any, Any], Any]] = None
    setup_fields: Tuple[str, ...] = ()
    frame: str = "ENU"
    hold: Optional[str] = None
    needs: Tuple[str, ...] = ("acc", "mag")
    shipped: Optional[str] = None
    module: str = ""
    check: Optional[Callable[[Any], None]] = None
    recorded: bool = True
    init_reads: Tuple[str, ...] = ()
    first_step: str = ""
    field_unit_gains: Tuple[str, ...] = ()
    advise: Optional[Callable[[Any, Any, Any], Optional[str]]] = None

    def gain(self, field: str) -> Gain:
        for g in self.gains:
            if g.field == field:
                return g
        raise ValueError(f"{field!r} is not a gain of {self.name} (gains: {[g.field for g in self.gains]})")

    def params(self, dtype=None):
        """The params used when none are given: the shipped gains file when there is one, else the defaults."""
        if self.shipped is not None:
            from ..fitting import gainsfile

            return gainsfile.load_shipped(self.shipped, self, dtype=dtype)
        return self.default_params(dtype=dtype)


#: name -> module (under jaxatt.observers) that declares it. The names are known without importing JAX.
INDEX: Dict[str, str] = {
    "batista-ges": "batista_ges",
    "batista-so3": "batista_so3",
    "complementary": "complementary",
    "madgwick": "madgwick",
    "mahony": "mahony",
    "mekf": "mekf",
    "nlo": "nlio",
    "nlio-fg": "nlio",
    "nlio": "nlio",
    "robust": "robust_ahrs",
    "vqf": "vqf",
    "vqf-6d": "vqf",
}

_EXTRA: Dict[str, Entry] = {}


def names(recorded: Optional[bool] = None) -> Tuple[str, ...]:
    """Registered names (``recorded=True``: only those set up for recorded data; needs their modules)."""
    all_names = tuple(INDEX) + tuple(n for n in _EXTRA if n not in INDEX)
    if recorded is None:
        return all_names
    return tuple(n for n in all_names if get(n).recorded == recorded)


def get(name: Union[str, Entry]) -> Entry:
    """The :class:`Entry` of ``name`` (ValueError listing the registered names)."""
    if isinstance(name, Entry):
        return name
    if name in _EXTRA:
        return _EXTRA[name]
    if name not in INDEX:
        raise ValueError(f"unknown observer {name!r}; registered: {', '.join(names())}")
    mod = importlib.import_module(f"{__package__}.{INDEX[name]}")
    for e in getattr(mod, "ENTRIES", ()):
        if e.name == name:
            return e
    raise ValueError(f"module jaxatt.observers.{INDEX[name]} declares no entry {name!r}")  # pragma: no cover


def markdown_table() -> str:
    """The table of the registered observers (name, module, reference, summary) in Markdown: the README's
    observers table is this text (``tests/test_docs.py`` checks it)."""
    rows = ["| name | module | reference | what it estimates |", "|---|---|---|---|"]
    for n in INDEX:
        e = get(n)
        rows.append(f"| `{e.name}` | `jaxatt.observers.{e.module}` | {e.reference} | {e.summary} |")
    return "\n".join(rows)


def register(entry: Entry) -> Entry:
    """Add an observer of your own to the registry (its name must be new); returns it.

    The entry is checked first (TypeError / ValueError, one line naming the field): ``make()`` gives an
    :class:`~jaxatt.types.Observer`, ``default_params(dtype=None)`` a NamedTuple holding every field that ``gains``,
    ``setup_fields``, ``first_step`` and ``field_unit_gains`` name, ``frame`` / ``hold`` / ``needs`` valid. The
    front door then checks its observer as it checks one passed directly (:func:`jaxatt.filter`)."""
    check_entry(entry)
    if entry.name in INDEX or entry.name in _EXTRA:
        raise ValueError(f"an observer named {entry.name!r} is already registered")
    _EXTRA[entry.name] = entry
    return entry


def builtin(entry: Entry) -> bool:
    """True for an observer jaxatt declares (tested with the package), False for one a user registered or
    changed (``entry._replace(...)``): the front door checks those as it checks a user's own observer."""
    return entry.name in INDEX and get(entry.name) is entry


def _takes_positional(fn, n: int, **keywords) -> bool:
    """Whether ``fn`` can be called with ``n`` positional arguments and ``keywords`` (True when it has no
    signature to tell, e.g. a builtin)."""
    import inspect

    try:
        inspect.signature(fn).bind(*range(n), **keywords)
    except TypeError:
        return False
    except ValueError:
        return True
    return True


def check_entry(entry) -> None:
    """TypeError / ValueError (one line, naming the field) unless ``entry`` is a usable :class:`Entry`."""
    from ..frames import FRAMES
    from ..types import HOLDS

    if not isinstance(entry, Entry):
        raise TypeError(
            f"register takes a jaxatt.observers.registry.Entry, got {type(entry).__name__} (wrap an Observer: "
            "Entry(name, summary, reference, make=lambda: observer, default_params=..., gains=(Gain(...), ...)))"
        )
    what = f"Entry {entry.name!r}"
    if not isinstance(entry.name, str) or not entry.name:
        raise ValueError(f"Entry.name must be a non-empty string, got {entry.name!r}")
    for field in ("make", "default_params"):
        if not callable(getattr(entry, field)):
            raise TypeError(f"{what}: {field} must be a function, got {type(getattr(entry, field)).__name__}")
    obs = entry.make()
    if not isinstance(obs, Observer):
        raise TypeError(f"{what}: make() must return a jaxatt.Observer, got {type(obs).__name__}")
    if entry.frame not in FRAMES:
        raise ValueError(f"{what}: frame must be one of {', '.join(FRAMES)}, got {entry.frame!r}")
    for where, hold in (("hold", entry.hold), ("make().hold", obs.hold)):
        if hold is not None and hold not in HOLDS:
            raise ValueError(f"{what}: {where} must be one of {', '.join(HOLDS)}, got {hold!r}")
    if entry.hold is not None and obs.hold is not None and entry.hold != obs.hold:
        raise ValueError(f"{what}: hold {entry.hold!r} differs from its observer's own ({obs.hold!r}): give it once")
    if not isinstance(entry.needs, tuple) or not set(entry.needs) <= {"acc", "mag"}:
        raise ValueError(f"{what}: needs must be a tuple of 'acc' / 'mag', got {entry.needs!r}")
    if not isinstance(entry.gains, tuple) or not all(isinstance(g, Gain) for g in entry.gains):
        got = [type(g).__name__ for g in entry.gains] if isinstance(entry.gains, (tuple, list)) else entry.gains
        raise TypeError(f"{what}: gains must be a tuple of registry.Gain(field, unit, doc, ...), got {got}")
    bad = [g.field for g in entry.gains if g.constraint not in CONSTRAINTS]
    if bad:
        raise ValueError(f"{what}: gain {bad[0]!r} has constraint not in {', '.join(CONSTRAINTS)}")
    if not callable(entry.default_params) or not _takes_positional(entry.default_params, 0, dtype=None):
        raise TypeError(f"{what}: default_params must take dtype= (default_params(dtype=None) -> Params)")
    try:
        p = entry.default_params(dtype=None)
    except Exception as e:
        raise TypeError(f"{what}: default_params(dtype=None) raised {type(e).__name__}: {e}") from None
    if entry.advise is not None and not _takes_positional(entry.advise, 3):
        raise TypeError(f"{what}: advise must take (params, outputs, samples)")
    fields = getattr(p, "_fields", None)
    if fields is None:
        raise TypeError(f"{what}: default_params() must return a NamedTuple of params, got {type(p).__name__}")
    named = [g.field for g in entry.gains] + list(entry.setup_fields) + list(entry.field_unit_gains)
    named += [entry.first_step] if entry.first_step else []
    missing = [f for f in named if f not in fields]
    if missing:
        raise ValueError(
            f"{what}: {missing[0]!r} is not a field of its params {type(p).__name__} ({', '.join(fields)})"
        )


# ------------------------------------------------------------------------------------------------------------
# Set-up on recorded data
# ------------------------------------------------------------------------------------------------------------
def first_sample_frame(sample):
    """(R0, m_nav, |a|) from the first acc / mag sample: the TRIAD start (sensor to ENU), the magnetic field in
    that ENU frame (the reference of the magnetometer) and the specific-force norm (the gravity reference)."""
    acc, mag = jnp.asarray(sample.acc), jnp.asarray(sample.mag)
    r0 = so3.triad(acc, mag, "ENU")
    return r0, so3.mv(r0, mag), jnp.sqrt(jnp.sum(acc * acc, axis=-1))


class _Recorded(NamedTuple):
    inner: Any
    fields: tuple

    @property
    def t(self):
        return self.inner.t


def _wrap(base: Observer, setup: Callable, fields: Tuple[str, ...], name: str) -> Observer:
    def fill(p, s):
        return p._replace(**dict(zip(fields, s.fields)))

    def init(p, sample):
        pt = setup(p, sample)
        return _Recorded(base.init(pt, sample), tuple(getattr(pt, f) for f in fields))

    def step(p, s, u, dt):
        inner, out = base.step(fill(p, s), s.inner, u, dt)
        return _Recorded(inner, s.fields), out

    def output(p, s):
        return base.output(fill(p, s), s.inner)

    if base.output is None:
        raise ValueError(f"observer {name!r} needs an output(params, state) function to be set up for recorded data")
    return Observer(init, step, name, output, base.time_reversed, base.hold)  # same params type: same time reversal


_WRAPPED: Dict[Any, Observer] = {}


def hold_of(entry) -> str:
    """The hold of ``entry`` (a name or :class:`Entry`): its own ``hold``, else its observer's, else "next"."""
    e = get(entry)
    return e.hold or e.make().hold or "next"


def with_hold(entry, observer: Observer) -> Observer:
    """``observer`` carrying the hold of ``entry`` (:func:`hold_of`) when it declares none."""
    return observer if observer.hold is not None else observer._replace(hold=hold_of(entry))


def recorded_observer(entry) -> Observer:
    """The observer of ``entry`` (a name or :class:`Entry`) as run on recorded data: ``init`` calls the entry's
    ``setup`` on the first sample and keeps the per-recording fields in the state, ``step`` puts them back into
    the params it is given (so gradients reach every other field). The entry's own observer when it has no
    set-up. Cached: the same entry gives the same Observer (jitted runners are reused)."""
    e = get(entry)
    if not e.recorded:
        raise ValueError(
            f"observer {e.name!r} is not set up for recorded data (it needs the references and gains of "
            "its paper): pass the Observer and its params yourself"
        )
    if e.setup is None:
        return with_hold(e, e.make())
    try:  # by the entry, not its name: a changed or re-registered entry gets its own
        key: Any = (e, hash(e))[0]
    except TypeError:  # an unregistered entry holding a list
        key = e.name
    if key not in _WRAPPED:
        _WRAPPED[key] = with_hold(e, _wrap(e.make(), e.setup, tuple(e.setup_fields), e.name))
    return _WRAPPED[key]

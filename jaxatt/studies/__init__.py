"""The papers' simulation studies, one typed object each (:class:`jaxatt.studies.base.Study`): configuration,
scenario, compared observers, errors, published numbers and tables; :func:`get` by name.

* ``batista-ges``, ``batista-so3``: Section IV / 4 of the two Batista et al. (2019) papers (NED, nT).
* ``nlio-case1`` ... ``nlio-case4``, ``nlio-simb``: Section 5 of the sensors2020 NLIO paper.
* ``complementary``: Trumpf et al. (2012) on the vector-measurement scenarios of :mod:`jaxatt.sim.references`.
* ``ahrs``: a registered AHRS filter (Madgwick, Mahony, VQF, the robust AHRS, ...) on a simulated IMU (ENU).
"""

from __future__ import annotations

import importlib

from .base import Setup, Study, evaluate, reproduce

__all__ = ["Study", "Setup", "reproduce", "evaluate", "get", "NAMES", "PAPER_STUDIES", "TUNABLE"]

#: study name -> module (imported on first use).
_MODULES = {
    "batista-ges": "batista_ges",
    "batista-so3": "batista_so3",
    "nlio-case1": "nlio",
    "nlio-case2": "nlio",
    "nlio-case3": "nlio",
    "nlio-case4": "nlio",
    "nlio-simb": "nlio",
    "complementary": "complementary",
    "ahrs": "ahrs",
}
NAMES = tuple(_MODULES)
#: The studies with published numbers (``jaxatt reproduce``).
PAPER_STUDIES = tuple(n for n in NAMES if n not in ("complementary", "ahrs"))
#: The studies ``jaxatt tune`` can tune (their tuned observer has declared gains and the study a loss).
TUNABLE = ("batista-ges", "batista-so3", "complementary", "nlio-case1", "nlio-case2", "nlio-case3")


def get(name: str) -> Study:
    """The :class:`Study` named ``name`` (ValueError listing the names)."""
    if isinstance(name, Study):
        return name
    if name not in _MODULES:
        raise ValueError(f"unknown study {name!r}; studies: {', '.join(NAMES)}")
    mod = importlib.import_module(f"{__package__}.{_MODULES[name]}")
    return mod.STUDIES[name] if hasattr(mod, "STUDIES") else mod.STUDY

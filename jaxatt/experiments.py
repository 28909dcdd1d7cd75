"""``jaxatt.experiments`` of version 0.1 is :mod:`jaxatt.studies` since 0.2 (the same modules: ``Config``,
``observer(cfg)``, ``params(cfg)``, ``scenario(cfg)``): this alias keeps 0.1 code (``from jaxatt.experiments
import batista_ges as E``) running, with a DeprecationWarning naming the new place."""

import sys
import warnings

from .studies import batista_ges, batista_so3, complementary, nlio

for _module in (batista_ges, batista_so3, complementary, nlio):  # import jaxatt.experiments.batista_ges, as in 0.1
    sys.modules[f"{__name__}.{_module.__name__.rsplit('.', 1)[1]}"] = _module

warnings.warn(
    "jaxatt.experiments is jaxatt.studies since 0.2: import from there (from jaxatt.studies import batista_ges)",
    DeprecationWarning,
    stacklevel=2,
)

"""Where the tests find the BROAD trials (../shared/data/broad), and the rule for a missing data set: skip on a
developer's machine, fail in CI (CI=true), which must have it."""

import os
from pathlib import Path

import pytest

DATA = Path(__file__).parents[1] / ".." / "shared" / "data" / "broad"
PUBLISHED = DATA / "published" / "results_mahony_average_rmse.json"


def need_data():
    """Skip without the BROAD files or h5py, except under CI=true, where that is a failure."""
    reason = None
    if not (DATA.is_dir() and any(DATA.glob("*.hdf5"))):
        reason = f"BROAD data not found in {DATA}"
    else:
        try:
            import h5py  # noqa: F401
        except ImportError:
            reason = "h5py is not installed (pip install '.[test]')"
    if reason is not None:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(f"{reason} (CI=true: the BROAD tests must run)")
        pytest.skip(reason)

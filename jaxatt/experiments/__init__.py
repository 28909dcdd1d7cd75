"""Paper set-ups as experiments (scenario + observer + params + errors + published numbers)."""
from . import batista_ges  # noqa: F401

REGISTRY = {batista_ges.NAME: batista_ges}

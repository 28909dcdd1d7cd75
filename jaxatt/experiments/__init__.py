"""Paper set-ups as experiments (scenario + observer + params + errors + published numbers)."""
from . import batista_ges, batista_so3  # noqa: F401

REGISTRY = {batista_ges.NAME: batista_ges, batista_so3.NAME: batista_so3}

"""Paper set-ups as experiments (scenario + observer + params + errors + published numbers)."""
from . import batista_ges, batista_so3, complementary  # noqa: F401

REGISTRY = {m.NAME: m for m in (batista_ges, batista_so3, complementary)}

"""The ``jaxatt`` command's first lines: Ctrl-C before :func:`jaxatt.cli.entry` has installed its handler (while
numpy, JAX and the CLI are imported) exits 130 at once, without a traceback; nothing has been computed yet."""

import os
import signal


def main() -> None:
    signal.signal(signal.SIGINT, lambda signum, frame: os._exit(130))
    from .cli import entry

    entry()

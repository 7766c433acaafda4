"""``python -m jaxusar``: the same as the ``jaxusar`` command."""

import sys

from jaxusar.cli import main

sys.exit(main())

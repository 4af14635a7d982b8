"""``python -m volshade``: the ``volshade`` command (:mod:`volshade.cli`)."""

import sys

from .cli import main

sys.exit(main())

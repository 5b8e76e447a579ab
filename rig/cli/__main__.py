"""``python -m rig.cli``: the ``rig`` command (tests and child processes start it this way)."""

import sys

from rig.cli import main

sys.exit(main())

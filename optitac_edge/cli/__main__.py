"""``python -m optitac_edge.cli``: the ``optitac-edge`` command."""

import sys

from optitac_edge.cli import main

sys.exit(main())

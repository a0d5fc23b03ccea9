"""``python -m seamap`` is the ``seamap`` console script."""

import sys

from seamap.cli import main

sys.exit(main())

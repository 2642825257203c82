"""``python -m sysid_bench``: the ``sysid-bench`` command line."""

import sys

from sysid_bench.apps.cli import main

sys.exit(main())

"""``python -m sysid_bench``: the ``sysid-bench`` command line."""

import sys

from sysid_bench.cli import main

sys.exit(main())

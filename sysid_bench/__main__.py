"""``python -m sysid_bench ...``: the same as the ``sysid-bench`` command."""

import sys

from sysid_bench.cli import main

sys.exit(main())

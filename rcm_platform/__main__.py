"""``python3 -m rcm_platform``: the agent ``rcmp_n`` with the same options (CONTRACTS §1)."""

import sys

from rcm_platform.rcmp_node import main

sys.exit(main())

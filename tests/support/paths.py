"""Where things are: the repository's root folder, for tests at any depth of ``tests/``."""

import os

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

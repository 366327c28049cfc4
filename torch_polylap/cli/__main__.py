"""``python -m torch_polylap.cli``: the ``polylap`` command."""

import sys

from . import main

sys.exit(main())

"""``python -m torchdoct.cli``: the ``torchdoct`` command line."""

import sys

from . import main

sys.exit(main())

"""`python -m cellctl.cli ...`: the same as `cellctl ...`."""

import sys

from . import main

sys.exit(main())

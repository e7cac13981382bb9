"""`python -m cellctl.cli ...`: the same as `cellctl ...`."""

import sys

from cellctl.cli import main

sys.exit(main())

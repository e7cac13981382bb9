"""`python -m drivers.sim.servers.ur`: a simulated UR controller until SIGTERM (exit status 0)."""

import sys

from drivers.sim.servers.ur.server import main

sys.exit(main())

#!/usr/bin/env python3
"""Fit the latent manifold of a database of measured materials (paper Sec. 3) and save it.

The tool is mitsuba_manifold/apps/cli/fit_manifold.py (also installed as a console script); --help lists its options.
"""

import os
import sys

# Run from a checkout without installing the package: its root comes first on the path.
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from mitsuba_manifold._util import interrupts  # noqa: E402

# Ctrl-C while Python imports the tool, before it can write anything: one line, no traceback.
interrupts.exit_while_starting()

from mitsuba_manifold.apps.cli.fit_manifold import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())

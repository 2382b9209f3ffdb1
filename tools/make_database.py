#!/usr/bin/env python3
"""Make a database folder from built-in sets (merl, rgl, nielsen, all, sgd) and measured files.

The tool is mitsuba_manifold/apps/cli/make_database.py (also installed as a console script); --help lists its options.
"""

import os
import sys

# Run from a checkout without installing the package: its root comes first on the path.
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from mitsuba_manifold._util import interrupts  # noqa: E402

# Ctrl-C while Python imports the tool, before it can write anything: one line, no traceback.
interrupts.exit_while_starting()

from mitsuba_manifold.apps.cli.make_database import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())

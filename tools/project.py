#!/usr/bin/env python3
"""Project a MERL table onto a manifold: the latent point whose material is closest.

The tool is mitsuba_manifold/apps/cli/project.py (also installed as a console script); --help lists its options.
"""

import os
import sys

# Run from a checkout without installing the package: its root comes first on the path.
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from mitsuba_manifold._util import interrupts  # noqa: E402

# Ctrl-C while Python imports the tool, before it can write anything: one line, no traceback.
interrupts.exit_while_starting()

from mitsuba_manifold.apps.cli.project import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())

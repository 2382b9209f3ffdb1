#!/usr/bin/env python3
"""Blend a basis of per-material renders into the image of a latent point (paper Eq. 13).

The tool is mitsuba_manifold/apps/cli/blend.py (also installed as a console script); --help lists its options.
"""

import os
import sys

# Run from a checkout without installing the package: its root comes first on the path.
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from mitsuba_manifold._util import interrupts  # noqa: E402

# Ctrl-C while Python imports the tool, before it can write anything: one line, no traceback.
interrupts.exit_while_starting()

from mitsuba_manifold.apps.cli.blend import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())

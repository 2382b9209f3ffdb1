#!/usr/bin/env python3
"""Explore a material manifold in the browser: drag a latent point, see the material in the scene.

The tool is mitsuba_manifold/apps/cli/explore.py (also installed as a console script); --help lists its options.
"""

import os
import sys

# Run from a checkout without installing the package: its root comes first on the path.
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from mitsuba_manifold.apps.cli.explore import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env python3
"""Refit and write the manifolds that ship with the package (mitsuba_manifold/manifold/shipped/).

The tool is mitsuba_manifold/apps/cli/build_manifolds.py; --help lists its options.
"""

import os
import sys

# Run from a checkout: its root comes first on the path (the files go into that checkout).
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from mitsuba_manifold.apps.cli.build_manifolds import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())

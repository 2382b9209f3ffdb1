#!/usr/bin/env python3
"""Find the latent point whose blend best matches a target image (see mitsuba_manifold/cli/match.py)."""

import sys

import _cli  # noqa: F401  (puts the checkout on sys.path)
from mitsuba_manifold.cli.match import main

if __name__ == "__main__":
    sys.exit(main())

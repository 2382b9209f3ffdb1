#!/usr/bin/env python3
"""Benchmarks (not timed tests): tools/bench.py NAME --json OUT.

The tool is benchmarks/cli.py; --help lists its options.
"""

import os
import sys

# Run from a checkout without installing the package: its root comes first on the path.
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from mitsuba_manifold._util import interrupts  # noqa: E402

# Ctrl-C while Python imports the tool, before it can write anything: one line, no traceback.
interrupts.exit_while_starting()

from benchmarks.cli import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())

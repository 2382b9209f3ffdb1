#!/usr/bin/env python3
"""The main job on the built-in default data, end to end (database, manifold, basis, blends).

The tool is mitsuba_manifold/apps/cli/main_job.py (also installed as a console script); --help lists its options.
"""

import os
import signal
import sys

# Ctrl-C while Python imports the tool, before it can write anything: one line, no traceback.
signal.signal(
    signal.SIGINT,
    lambda *_: (
        sys.stderr.write("error: interrupted while starting; nothing was written\n"),
        os._exit(130),
    ),
)
# Run from a checkout without installing the package: its root comes first on the path.
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from mitsuba_manifold.apps.cli.main_job import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())

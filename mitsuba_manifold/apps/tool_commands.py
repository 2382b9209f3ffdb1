"""The command lines of the tools, as a user pastes them (printed by the main job, the explorer's
hints): shared by the pipeline and the command-line tools, so that neither imports the other.
"""

import os
import shlex

from ..manifold.file.shipped import resolve_manifold

#: The checkout's ``tools/`` folder (absent in an installed wheel: the console scripts instead).
TOOLS_DIR = os.path.join(
    os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "tools"
)


def tool_command(tool, script):
    """The words that start ``tool`` (``"explore"``): ``python3 <checkout>/tools/<script>`` when
    the package runs from a checkout, else the ``mitsuba-manifold <tool>`` console script.
    """
    path = os.path.join(TOOLS_DIR, script)
    return ["python3", path] if os.path.isfile(path) else ["mitsuba-manifold", tool]


def explore_command(basis, manifold=None):
    """The explore command line for a basis, with absolute paths so that it works pasted from
    any folder.
    """
    parts = tool_command("explore", "explore.py") + ["--basis", os.path.abspath(basis)]
    if manifold:
        parts += ["--manifold", os.path.abspath(resolve_manifold(manifold))]
    return shlex.join(parts)

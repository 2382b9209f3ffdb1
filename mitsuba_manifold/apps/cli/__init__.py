"""Command-line tools: one module per tool, each with ``main(argv)``.

``tools/<tool>.py`` (the documented interface) and the console scripts installed with the
package (``mitsuba-manifold <tool> ...`` and ``mm-<tool>``) all call these.
"""

from __future__ import annotations

import importlib
import sys

#: Subcommand -> module of this package.
TOOLS = {
    "make-database": "make_database",
    "fit": "fit_manifold",
    "project": "project",
    "render-basis": "render_basis",
    "blend": "blend",
    "match": "match",
    "main": "main_job",
    "make-scene-meshes": "make_scene_meshes",
    "explore": "explore",
}


#: What else a user may type for a tool: the module's and the script's name (``render_basis``,
#: ``fit_manifold``, ``main_job``), spelled with ``_`` or ``-``.
ALIASES = {
    spelling: tool
    for tool, module in TOOLS.items()
    for name in (tool, module)
    for spelling in (name, name.replace("-", "_"), name.replace("_", "-"))
}


def main(argv=None) -> int:
    """``mitsuba-manifold TOOL [args...]``: run one tool (also named as its script,
    ``render_basis``).
    """
    argv = sys.argv[1:] if argv is None else list(argv)
    usage = (
        "usage: mitsuba-manifold {" + ",".join(TOOLS) + "} [args...]\n\n"
        "Run 'mitsuba-manifold TOOL --help' for a tool's options."
    )
    if argv and argv[0] in ("-h", "--help"):
        print(usage)
        return 0
    if argv and argv[0] in ALIASES:
        argv[0] = ALIASES[argv[0]]
    if not argv or argv[0] not in TOOLS:
        from ...errors import did_you_mean

        what = (
            f"unknown tool {argv[0]!r}{did_you_mean(argv[0], TOOLS)}" if argv else "no tool given"
        )
        print(f"error: {what}; one of: {', '.join(TOOLS)}\n{usage}", file=sys.stderr)
        return 2
    # argparse names the program after argv[0]: make usage lines read "mitsuba-manifold fit ...".
    sys.argv = [f"mitsuba-manifold {argv[0]}"] + argv[1:]
    return importlib.import_module(f"{__name__}.{TOOLS[argv[0]]}").main(argv[1:])

"""Command-line tools: one module per tool, each with ``main(argv)``.

``tools/<tool>.py`` (the documented interface) and the console scripts installed with the
package (``mitsuba-manifold <tool> ...`` and ``mm-<tool>``) all call these.
"""

import importlib
import sys

#: Subcommand -> module of this package.
TOOLS = {
    "make-database": "make_database",
    "fit": "fit_manifold",
    "render-basis": "render_basis",
    "blend": "blend",
    "match": "match",
    "main": "main_job",
    "bench": "bench",
    "make-scene-meshes": "make_scene_meshes",
    "explore": "explore",
}


def main(argv=None):
    """``mitsuba-manifold TOOL [args...]``: run one tool."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in TOOLS:
        print("usage: mitsuba-manifold {" + ",".join(TOOLS) + "} [args...]\n\n"
              "Run 'mitsuba-manifold TOOL --help' for a tool's options.",
              file=sys.stderr if argv and argv[0] not in ("-h", "--help") else sys.stdout)
        return 0 if argv and argv[0] in ("-h", "--help") else 2
    return importlib.import_module(f"{__name__}.{TOOLS[argv[0]]}").main(argv[1:])

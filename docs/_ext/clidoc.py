"""The command-line reference, generated from the tools' own argparse parsers at build time.

Every ``tools/*.py`` script names the module whose ``main(argv)`` it runs. This extension imports
that module, runs ``main`` with argparse's ``parse_args`` replaced by a function that hands the
parser back instead of parsing, and writes ``reference/cli.md`` from ``parser.format_help()``:
the page shows exactly what ``--help`` prints. Nothing here lists the tools by hand, so a tool
added, removed or renamed shows up on the next build.
"""

import argparse
import ast
import contextlib
import importlib
import io
import os
import re
import textwrap

from generated import write_page

#: The user's tools, in the order of the page (the others follow by name; ``bench`` comes last).
FIRST = ("main", "render_basis", "blend", "explore", "match", "fit_manifold", "project")
#: The last tool of the page: the benchmarks, for developers.
LAST = ("bench",)
#: Width of the help texts (fits a code block of the documentation's page).
COLUMNS = "78"

#: Options whose presence makes a tool hand over to another parser (``match.py --render``).
SUB_MODES = {"match": [["--render"]]}


class _Captured(BaseException):
    """Raised in place of parsing: carries the parser (a BaseException so no tool catches it)."""

    def __init__(self, parser):
        super().__init__()
        self.parser = parser


def _capture(self, args=None, namespace=None):
    raise _Captured(self)


def tool_module(script):
    """The module whose ``main`` the tool script ``script`` runs (from its import line)."""
    tree = ast.parse(open(script, encoding="utf-8").read(), script)
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and any(a.name == "main" for a in node.names):
            return node.module
    raise RuntimeError(f"{script}: no 'from MODULE import main' line")


def parser_of(module, argv=()):
    """The argparse parser ``module.main(argv)`` builds, without running the tool."""
    main = importlib.import_module(module).main
    saved = argparse.ArgumentParser.parse_args
    argparse.ArgumentParser.parse_args = _capture
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            main(list(argv))
    except _Captured as c:
        return c.parser
    finally:
        argparse.ArgumentParser.parse_args = saved
    raise RuntimeError(f"{module}.main built no parser")


def tools(root):
    """``[(name, script, module)]`` of every ``tools/*.py``, sorted by name."""
    folder = os.path.join(root, "tools")
    out = []
    for f in sorted(os.listdir(folder)):
        if f.endswith(".py") and not f.startswith("_"):
            script = os.path.join(folder, f)
            out.append((f[:-3], script, tool_module(script)))
    return out


def console_commands():
    """``{module: subcommand}`` of the ``mitsuba-manifold`` console command (its dispatcher's table)."""
    from mitsuba_manifold.apps.cli import TOOLS

    return {f"mitsuba_manifold.apps.cli.{module}": tool for tool, module in TOOLS.items()}


def _fit(text, width):
    """``text`` with every line longer than ``width`` wrapped (descriptions that argparse prints
    as written), continuation lines indented as the line they continue.
    """
    out = []
    for line in text.splitlines():
        if len(line) <= width:
            out.append(line)
            continue
        indent = line[: len(line) - len(line.lstrip())]
        item = re.match(r"\s*(\d+\.|-) ", line)
        more = " " * len(item.group(0)) if item else indent
        out += textwrap.wrap(line, width, subsequent_indent=more, break_on_hyphens=False)
    return "\n".join(out) + "\n"


def help_text(parser, prog):
    parser.prog = prog
    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = COLUMNS
    try:
        return _fit(parser.format_help(), int(COLUMNS))
    finally:
        if old is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = old


def page(root):
    """The Markdown of the command-line reference."""
    lines = [
        "# Command-line tools",
        "",
        "Every tool is a script in `tools/` (run it from a checkout: `python3 tools/NAME.py`). "
        "Once the package is installed, the tools below that name a console command are also "
        "`mitsuba-manifold COMMAND` (most also `mm-COMMAND`: `[project.scripts]` in "
        "`pyproject.toml`; the script's own name works too: "
        "`mitsuba-manifold render_basis`); the others run from a checkout only. This page is "
        "generated from the tools' own argument parsers when the documentation is built: it is "
        "what `--help` prints.",
        "",
    ]
    commands = console_commands()

    def order(tool):
        name = tool[0]
        return (name in LAST, FIRST.index(name) if name in FIRST else len(FIRST), name)

    for name, _script, module in sorted(tools(root), key=order):
        variants = [()] + [tuple(v) for v in SUB_MODES.get(name, [])]
        command = commands.get(module)
        installed = (
            f"Installed as `mitsuba-manifold {command}`."
            if command
            else "From a checkout only (no console command)."
        )
        for argv in variants:
            title = " ".join([f"tools/{name}.py", *argv])
            lines += [
                f"## `{title}`",
                "",
                f"Module: `{module}`. {installed}",
                "",
                "```text",
                help_text(parser_of(module, argv), f"python3 {title}").rstrip(),
                "```",
                "",
            ]
    return "\n".join(lines)


def _write(app):
    write_page(app, "cli.md", page(os.path.dirname(app.srcdir)))


def setup(app):
    app.connect("builder-inited", _write)
    return {"parallel_read_safe": True, "parallel_write_safe": True}

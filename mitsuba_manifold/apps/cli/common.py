"""Argument helpers shared by the command-line tools (parsing and progress only; the work is in the library)."""

from __future__ import annotations

import argparse
import functools
import os
import re
import sys
from typing import TYPE_CHECKING, NoReturn

from ..._util.interrupts import INTERRUPTED, Noted
from ..._util.names import is_name
from ...data.sources import MeasuredFile, register_reader
from ...errors import MitsubaManifoldError, one_line

if TYPE_CHECKING:
    from collections.abc import Callable
    from typing import Any

    import numpy as np


#: What a tool reports as a one-line error (anything else is a bug and keeps its traceback).
ERRORS = (MitsubaManifoldError, OSError)
#: What a tool stopped by Ctrl-C says.
INTERRUPTED_MESSAGE = (
    "interrupted; every file listed so far is complete (run the same command again to resume)"
)


#: What argparse takes for a negative number, not an option: anything that starts like one
#: (``-1.1,-0.2``, ``-.5``, ``-1e-3 0.5``), the rule of argparse itself from Python 3.13
#: (``re.compile(r"-\.?\d")``, matched at the start); no tool has an option spelled so.
_NUMBERS = re.compile(r"-\.?\d")


def read_measured(path, dims) -> np.ndarray:
    """The reader of Mitsuba ``measured`` files (``.bsdf``) for every tool: Mitsuba is imported
    (:mod:`mitsuba_manifold.render`) only when a tool reads such a file, so that a database or
    material given by any tool may hold them.
    """
    from ...render.plugin import measured

    return measured.resample(path, dims)


register_reader(MeasuredFile.kind, read_measured)


#: The parser of the running tool: :func:`fail` names its options in library messages.
_ACTIVE: list = []

#: A Python parameter named in a library message (:mod:`mitsuba_manifold.errors`): `name`.
_PARAM = re.compile(r"`([A-Za-z_][A-Za-z0-9_]*)`")


class ArgumentParser(argparse.ArgumentParser):
    """argparse with its errors as one line ``error: ...`` (exit 2), as every other error,
    and negative numbers (also comma-separated lists of them) read as values, not options
    (argparse's own matcher set to its Python 3.13 rule, :data:`_NUMBERS`).

    ``aliases`` maps library parameter names to this tool's options where the option's
    ``dest`` differs (``{"scene_path": "scene"}``): library messages name Python
    parameters, and :func:`fail` writes the tool's option instead.

    ``renamed`` maps an option's former spelling to its name now (``{"--target": "--image"}``):
    both are option strings of one argument (the name first), and a command line that uses the
    former spelling works and says on stderr what it is now spelled.
    """

    def __init__(self, *args, aliases=None, renamed=None, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = _NUMBERS
        self.aliases = dict(aliases or {})
        self.renamed = dict(renamed or {})

    def parse_args(self, args=None, namespace=None):  # argparse overloads it: left unannotated
        _ACTIVE[:] = [self]
        parsed = super().parse_args(args, namespace)
        given = sys.argv[1:] if args is None else list(args)
        for old, new in self.renamed.items():
            if any(a == old or a.startswith(old + "=") for a in given):
                print(
                    f"note: {old} is now spelled {new}; the old spelling goes in the next release",
                    file=sys.stderr,
                )
        return parsed

    def option_names(self) -> dict[str, str]:
        """Python parameter (argparse ``dest`` or alias) -> the option a user types (its name
        now, not a former spelling).
        """
        names = {}
        for action in self._actions:
            if action.option_strings:
                current = [o for o in action.option_strings if o not in self.renamed]
                names[action.dest] = max(current or action.option_strings, key=len)
            elif action.dest != "help":
                names[action.dest] = (
                    action.metavar if isinstance(action.metavar, str) else action.dest
                )
        for param, dest in self.aliases.items():
            if dest in names:
                names[param] = names[dest]
        return names

    def error(self, message) -> NoReturn:
        self.exit(2, f"error: {message} (see {self.prog} --help)\n")


def add_prune_argument(parser) -> None:
    """``--prune``: the pruning budget of the blends a tool shows, the plugin's default and rule."""
    from ...manifold.pruning import DEFAULT_PRUNE

    parser.add_argument(
        "--prune",
        type=float,
        default=DEFAULT_PRUNE,
        help=f"pruning budget (default {DEFAULT_PRUNE:g}, as the plugin): blend the fewest materials "
        "such that each albedo channel changes by at most half of it and the cosine-weighted and "
        "raw table by at most it, relatively",
    )


def parse_list(text) -> list:
    """'a,b,c' -> ['a', 'b', 'c']."""
    items = [t.strip() for t in text.split(",") if t.strip()]
    if not items:
        raise argparse.ArgumentTypeError(f"expected a comma-separated list, got {text!r}")
    return items


def parse_indices(text) -> list[int]:
    """'0,3' -> [0, 3] (integers >= 0)."""
    try:
        values = [int(v) for v in parse_list(text)]
    except ValueError:
        values = [-1]
    if min(values) < 0:
        raise argparse.ArgumentTypeError(f"expected indices like 0,3 (integers >= 0), got {text!r}")
    return values


def parse_resolution(text) -> tuple[int, int, int]:
    """'90,90,180' -> (90, 90, 180)."""
    try:
        dims = tuple(int(v) for v in text.split(","))
    except ValueError:
        dims = ()
    if len(dims) != 3 or min(dims) < 1:
        raise argparse.ArgumentTypeError(
            f"resolution must be three positive integers like 90,90,180, got {text!r}"
        )
    return dims


def parse_floats(text) -> list:
    """'0.3, -1.2' or '0.3 -1.2' -> [0.3, -1.2]; an empty place between commas ('0,,1') is refused."""
    parts = re.split(r"\s*,\s*|\s+", text.strip())
    if "" in parts:
        raise argparse.ArgumentTypeError(
            f"{text!r} has an empty place between commas; expected numbers like '0.3,-1.2'"
        )
    try:
        return [float(v) for v in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected numbers like '0.3,-1.2', got {text!r}"
        ) from None


def parse_point(text) -> str | list[float]:
    """One latent point as every tool takes it: numbers (``'0.3,-1.2'``, ``'0.3 -1.2'``) or a
    material's name (one word that does not start like a number), resolved with the manifold
    by the library (:meth:`~mitsuba_manifold.manifold.model.Manifold.point`).
    """
    return text.strip() if is_name(text) else parse_floats(text)


def parse_points(groups, option="--x") -> list:
    """The points of a repeatable option taking several words (``--x A B --x 0.3 -1.2``), in
    order: each group is one point (numbers or a name), or several names, one point each.
    """
    points = []
    for group in groups:
        words = " ".join(group).replace(",", " ").split()
        names = [w for w in words if is_name(w)]
        if not names:
            points.append(parse_floats(" ".join(group)))
        elif len(names) == len(words):
            points.extend(names)
        else:
            raise argparse.ArgumentTypeError(
                f"{' '.join(group)!r} mixes material names and numbers; repeat {option} once per "
                f"point ({option} NAME {option} 0.3,-1.2)"
            )
    return points


def resolve_names(points, manifold) -> list | None:
    """``points`` (:func:`parse_points`) as one flat list of numbers, each name replaced by its
    latent point (q numbers).
    """
    if points is None:
        return None
    return [float(c) for v in points for c in (manifold.point(v) if isinstance(v, str) else v)]


def cli_message(error, parser=None) -> str:
    """``error`` as one line for a command-line user: each Python parameter the library named
    (`spp`) becomes the option that sets it (``--spp``), or plain text where none does.
    """
    parser = parser or (_ACTIVE[0] if _ACTIVE else None)
    names: dict[str, str] = parser.option_names() if parser is not None else {}
    return _PARAM.sub(lambda m: names.get(m.group(1), m.group(1)), one_line(error))


def fail(error, code=2) -> NoReturn:
    """Print an error for the user (one line, in the tool's option names) and exit."""
    print(f"error: {cli_message(error)}", file=sys.stderr)
    sys.exit(code)


def _interrupted(process) -> None:
    """Report Ctrl-C and exit 130. A whole process ends at once (its files are closed and its
    locks released by then): an extension module whose import the interrupt cut half-way
    would abort the interpreter's shutdown.
    """
    print(f"error: {INTERRUPTED_MESSAGE}", file=sys.stderr)
    if process:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(INTERRUPTED)
    sys.exit(INTERRUPTED)


def guarded(main) -> Callable[..., Any]:
    """Run a tool's ``main`` so that what goes wrong because of its input ends as one
    ``error:`` line: the package's errors and files the system refuses (:data:`ERRORS`),
    memory (exit 2), and Ctrl-C at any moment, imports included (exit 130). Anything else
    is a bug and keeps its traceback. Run as a process (``argv`` None), a Ctrl-C after
    ``main`` returned is ignored: everything was written, and the tool exits 0.
    """

    @functools.wraps(main)
    def run(argv=None):
        interrupts = Noted().install()
        finished = False
        try:
            result = main(argv)
            finished = True
            return result
        except KeyboardInterrupt:
            _interrupted(argv is None)
        except MemoryError:
            fail("out of memory; choose smaller sizes (resolution, --steps, --spp per pass)")
        except ERRORS as e:
            if interrupts.seen:
                _interrupted(argv is None)
            fail(e)
        except Exception:
            if interrupts.seen:  # an import cut by Ctrl-C
                _interrupted(argv is None)
            raise
        finally:
            interrupts.restore(finished_process=finished and argv is None)

    return run


class one_line_warnings:
    """Library warnings (an older L1- basis) as one ``warning: ...`` line on stderr."""

    def __enter__(self) -> None:
        import warnings

        self.catch = warnings.catch_warnings(record=True)
        self.caught = self.catch.__enter__()
        warnings.simplefilter("always", UserWarning)

    def __exit__(self, *exc) -> None:
        self.catch.__exit__(*exc)
        for w in self.caught:
            print(f"warning: {w.message}", file=sys.stderr)


#: Most files listed one per line; more are written under a progress bar.
LIST_FILES = 50


def write_outputs(tool, out, outputs, force=False, group=None) -> None:
    """Write ``outputs`` (``(kind, path, writer)``) as ``tool`` under the tools' output
    discipline (:class:`mitsuba_manifold._util.ownership.Outputs`): check
    that none replaces a file this tool did not make, create the folder of ``out``, run every
    writer (reporting each file, or more than :data:`LIST_FILES` with a progress bar and one
    line), each file recorded as the tool's own as it is written (a run
    stopped half-way leaves files the same command replaces). With ``group`` (what the run
    writes, e.g. ``"path:" + out``), the files an earlier run of the group wrote and this one
    did not are removed (a shorter ``--path``'s surplus frames).
    """
    from tqdm import tqdm

    from ..._util import ownership

    with ownership.Outputs(tool, force, group=group) as guard:
        for kind, path, _ in outputs:
            guard.check(path, kind)
        os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
        many = len(outputs) > LIST_FILES
        bar = tqdm(
            total=len(outputs), desc="writing", unit="file", disable=not many, file=sys.stderr
        )
        with bar:
            for kind, path, write in outputs:
                write()
                bar.update()
                if not many:
                    print(f"wrote {kind}: {path}")
        if many:
            print(f"wrote {len(outputs)} files: {outputs[0][1]} ... {outputs[-1][1]}")
        if group is not None:
            for path in guard.remove_stale(os.path.dirname(os.path.abspath(out))):
                print(
                    f"removed {path} (from an earlier {tool.removesuffix('.py')} to {out}; this one did not write it)"
                )

"""The files a blend writes, named before any work: its plan of outputs.

The image of a point goes to ``<stem>.exr`` (``<stem>.png`` beside it, tonemapped), its
reference and error images beside it (:data:`COMPANIONS`); the images along a path go to
``<stem>_<s>.exr`` frames (:func:`frame_names`, ``s`` zero-padded to the widest) and a contact
sheet ``<stem>_sheet.png``. :func:`planned_files` lists what a run will write, so that every
file is checked (:func:`mitsuba_manifold._util.ownership.check_replaceable`) before the inputs
are read; what may be replaced or removed is :mod:`mitsuba_manifold._util.ownership`'s rule.
"""

import os
import re
from dataclasses import dataclass
from typing import Optional

from ..errors import InputError

#: Files a point blend may write beside ``<stem>.exr``.
COMPANIONS = (".png", "_error.exr", "_error.png", "_reference.exr", "_reference.png")
#: Most images along a path (one EXR file each, and a contact-sheet tile).
MAX_STEPS = 1000


def exr_stem(path) -> str:
    """``path`` without its ``.exr``."""
    return path[:-4] if path.lower().endswith(".exr") else path


@dataclass(frozen=True)
class Output:
    """Where and how the images are written: ``out`` (an ``.exr`` file), ``png`` (also
    tonemapped sRGB PNGs, ``exposure`` stops), ``force`` (replace files the tool did not write).
    """

    out: str
    png: bool = False
    exposure: float = 0.0
    force: bool = False

    @property
    def stem(self) -> str:
        """``out`` without its ``.exr``."""
        return exr_stem(self.out)

    def check(self, path: bool = False) -> None:
        """Raise unless ``out`` names an ``.exr`` file (``path``: the frames of a path are named
        after it).
        """
        if not self.out.lower().endswith(".exr"):
            frames = " (with `path`: its frames are OUT_0.exr, OUT_1.exr, ...)" if path else ""
            raise InputError(
                f"`out` must name an .exr file{frames}, got {self.out!r}: use `out` {self.stem}.exr"
            )


def check_steps(steps: int) -> None:
    """Raise unless a path of ``steps`` images is from 2 to :data:`MAX_STEPS` long."""
    if not 2 <= steps <= MAX_STEPS:
        raise InputError(f"`steps` must be from 2 to {MAX_STEPS} (one EXR file each), got {steps}")


def frame_names(output: Output, steps: int) -> list:
    """The EXR frames of a path: ``<stem>_<s>.exr``, ``s`` zero-padded to the widest."""
    width = len(str(steps - 1))
    return [f"{output.stem}_{s:0{width}d}.exr" for s in range(steps)]


def existing_frames(output: Output, steps: int) -> list:
    """The frames of a path (EXR, and PNG with ``output.png``) that exist already, found by
    listing their folder (not by trying every step).
    """
    width = len(str(steps - 1))
    frame = re.compile(
        re.escape(os.path.basename(output.stem)) + r"_(\d{" + str(width) + r"})\.(exr|png)$"
    )
    folder = os.path.dirname(os.path.abspath(output.out))
    names = os.listdir(folder) if os.path.isdir(folder) else []
    found = [(n, frame.match(n)) for n in names]
    return [
        os.path.join(os.path.dirname(output.out), n)
        for n, m in found
        if m and int(m.group(1)) < steps and (output.png or m.group(2) == "exr")
    ]


def planned_files(
    output: Output,
    path_steps: Optional[int] = None,
    render_reference: bool = False,
    reference: bool = False,
) -> list:
    """``(kind, path)`` of the files a blend will write, to check first: with a path of
    ``path_steps`` images, the first frame (every frame's name is as long), the frames that
    exist already (found without listing every step: ``steps`` is not yet checked against the
    memory) and the contact sheet; for a point, its image and PNG, the rendered reference
    (``render_reference``) and the error images (``reference``: compared with one).
    """
    stem, png = output.stem, output.png
    if path_steps is not None:
        first = f"{stem}_{0:0{len(str(path_steps - 1))}d}.exr"
        out = [("image", first)] + ([("png", first[:-4] + ".png")] if png else [])
        return (
            out
            + [("frame", p) for p in existing_frames(output, path_steps)]
            + [("contact sheet", stem + "_sheet.png")]
        )
    out = [("image", output.out)] + ([("png", stem + ".png")] if png else [])
    if render_reference:
        out += [("reference", stem + "_reference.exr")] + (
            [("reference PNG", stem + "_reference.png")] if png else []
        )
    if reference or render_reference:
        out += [("error image", stem + "_error.exr"), ("error PNG", stem + "_error.png")]
    return out


def companions(out) -> list:
    """The files a point blend to ``out`` may write beside it (:data:`COMPANIONS`)."""
    return [exr_stem(out) + suffix for suffix in COMPANIONS]

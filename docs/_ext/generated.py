"""Pages the documentation build writes (the command-line and file-format references)."""

import os


def write_page(app, name, text):
    """Write ``text`` to ``reference/NAME`` of the documentation's sources, unless the file already
    holds it (then its time is kept, so Sphinx does not rebuild the page).
    """
    path = os.path.join(app.srcdir, "reference", name)
    old = open(path, encoding="utf-8").read() if os.path.exists(path) else None
    if old != text:
        with open(path, "w", encoding="utf-8") as f:
            f.write(text)

"""The file-format reference (docs/reference/formats.md, generated) against the declared models."""

import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.join(ROOT, "docs", "_ext"))

import formatdoc  # noqa: E402


def test_the_page_names_every_key_of_every_format_with_its_rule():
    text = formatdoc.page()
    sections = text.split("\n## ")[1:]
    assert len(sections) == len(formatdoc.FORMATS)
    for (_, file, spec), section in zip(formatdoc.FORMATS, sections):
        model = formatdoc._model(spec)
        assert f"`{file}`" in section and spec.replace(":", ".") in section
        lines = section.split("\n### ")[0].splitlines()  # the top-level table
        for name, field in model.model_fields.items():
            row = next(ln for ln in lines if ln.startswith(f"| `{field.alias or name}` |"))
            assert field.description is None or formatdoc._cell(field.description) in row, row
    assert "- 1 to 2: the paper's GP interpolant" in text  # the manifold's declared upgrades

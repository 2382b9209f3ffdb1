"""The file-format reference, generated from the formats' declared models at build time.

Each JSON format the package writes is a pydantic model (:mod:`mitsuba_manifold._util.schema`);
this extension writes ``reference/formats.md`` from their JSON schemas
(``Model.model_json_schema()``): one table per object, each key with its type, whether it is
required and its rule, and the versions each format reads. Nothing here lists a key by hand.
"""

import importlib
import re

from generated import write_page

#: ``(title, file, "module:Model")`` of the page's formats, in its order.
FORMATS = (
    ("Basis folder", "manifest.json", "mitsuba_manifold.basis.folder.manifest:ManifestSchema"),
    (
        "Saved manifold",
        "the .npz file's meta entry",
        "mitsuba_manifold.manifold.file.schema:ManifoldMeta",
    ),
    ("Database folder", "sources.json", "mitsuba_manifold.data.database:SourceList"),
    ("Chunked render", "a chunk's manifest.json", "mitsuba_manifold.render.jobs.chunks:ChunkMark"),
)


def _model(spec):
    module, name = spec.split(":")
    return getattr(importlib.import_module(module), name)


def _kind(prop):
    """A property's JSON-schema type in a few words."""
    if "$ref" in prop:
        return f"[{prop['$ref'].rsplit('/', 1)[-1]}](#{prop['$ref'].rsplit('/', 1)[-1].lower()})"
    if "const" in prop:
        return f"`{prop['const']!r}`"
    if "enum" in prop:
        return " or ".join(f"`{v!r}`" for v in prop["enum"])
    if "anyOf" in prop:
        kinds = [_kind(p) for p in prop["anyOf"] if p.get("type") != "null"]
        null = any(p.get("type") == "null" for p in prop["anyOf"])
        return " or ".join(kinds) + (" or null" if null else "")
    kind = prop.get("type", "any")
    if kind == "array":
        items = prop.get("items") or prop.get("prefixItems", [{}])[0]
        return f"array of {_kind(items)}"
    if kind == "object" and isinstance(prop.get("additionalProperties"), dict):
        return f"object of {_kind(prop['additionalProperties'])}"
    return kind


def _cell(text):
    return " ".join(str(text).split()).replace("|", "\\|")


def _table(schema):
    required = set(schema.get("required", ()))
    lines = ["| key | type | required | rule |", "|---|---|---|---|"]
    for key, prop in schema.get("properties", {}).items():
        lines.append(
            f"| `{key}` | {_cell(_kind(prop))} | {'yes' if key in required else 'no'} "
            f"| {_cell(prop.get('description', ''))} |"
        )
    extra = schema.get("additionalProperties", True)
    lines += ["", "Other keys: " + ("kept as they are." if extra else "refused."), ""]
    return lines


def _summary(doc):
    """The first paragraph of a docstring, its reStructuredText roles as Markdown code."""
    text = " ".join((doc or "").strip().split("\n\n")[0].split())
    text = re.sub(r":\w+:`~?\.*([^`<]*?)\s*(<[^>]*>)?`", r"`\1`", text)
    return re.sub(r"``([^`]*)``", r"`\1`", text)


def page():
    """The Markdown of the file-format reference."""
    lines = [
        "# File formats",
        "",
        "The JSON files and entries the package writes, each declared once as a model with a "
        "`version`: files of every earlier version read (the upgrades below), and a file at "
        "fault is refused with one line naming the file, the key, the value and the fix. This "
        "page is generated from the models when the documentation is built; a key's rule is "
        "also the text of the error that refuses a value breaking it.",
        "",
    ]
    for title, file, spec in FORMATS:
        model = _model(spec)
        schema = model.model_json_schema(by_alias=True)
        lines += [f"## {title}: `{file}`", "", f"Model: `{spec.replace(':', '.')}`.", ""]
        lines += [_summary(model.__doc__), ""]
        if hasattr(model, "VERSION"):
            lines += [
                f"Versions (the tables show {model.VERSION}, the newest): {model.VERSIONS}",
                "",
            ]
            steps = [
                f"- {v} to {v + 1}: {re.sub(r'^To version [0-9]+: ', '', _summary(f.__doc__))}"
                for v, f in model.UPGRADES.items()
            ]
            if steps:
                lines += ["An earlier version is upgraded as it is read:", "", *steps, ""]
        lines += _table(schema)
        for name, sub in schema.get("$defs", {}).items():
            lines += [f"### {name}", "", _summary(sub.get("description", "")), ""]
            lines += _table(sub)
    return "\n".join(lines).rstrip() + "\n"


def _write(app):
    write_page(app, "formats.md", page())


def setup(app):
    app.connect("builder-inited", _write)
    return {"parallel_read_safe": True, "parallel_write_safe": True}

"""Declared file formats: each JSON format the package writes is a pydantic model.

A format is a subclass of :class:`FileSchema`: its fields are the JSON object's keys, each with
its type and its rule (the field's ``description`` says what a valid value is, and is the text
of the error when a value breaks the rule), a ``format`` name and a ``version``. Every version
this package wrote before reads: :attr:`FileSchema.UPGRADES` declares, per earlier version, the
function that turns such an object into one of the next version, and :meth:`FileSchema.upgrade`
applies them in turn. :meth:`FileSchema.checked` validates an object and turns the first fault
into the package's one-line error naming the file, the field, the value and the fix
(:func:`fault_message`); ``model_json_schema()`` of a format is its reference
(``docs/reference/formats.md`` is made from them by ``docs/_ext/formatdoc.py`` when the
documentation is built).
"""

import typing
from typing import Any, Callable, ClassVar

from pydantic import BaseModel, ConfigDict, ValidationError, field_validator

from ..errors import FormatError

__all__ = ["FileSchema", "fault_message"]


class FileSchema(BaseModel):
    """A JSON file format: its keys as fields (strict types: no ``true`` for an integer, no
    text for a number), keys it does not declare kept, a ``version`` and the upgrades from
    every earlier one.
    """

    model_config = ConfigDict(
        strict=True, extra="allow", frozen=True, validate_by_name=True, populate_by_name=True
    )

    #: The format's ``version`` this package writes (the newest it reads).
    VERSION: ClassVar[int] = 1
    #: ``{version: upgrade}``: ``upgrade(data)`` turns a JSON object of that earlier version
    #: into one of the next version (a new dict; the object read is not changed).
    UPGRADES: ClassVar[dict[int, Callable[[dict], dict]]] = {}
    #: What each version is, in a line (for the format's reference page).
    VERSIONS: ClassVar[str] = ""
    #: What the user does about a file that is refused (ends every error message).
    FIX: ClassVar[str] = ""
    #: The error class of a refused file.
    ERROR: ClassVar[type] = FormatError

    format: str
    version: int

    @field_validator("version")
    @classmethod
    def _known_version(cls, v: int) -> int:
        if not 1 <= v <= cls.VERSION:
            raise ValueError(f"is {v}, not a version this package reads (1 to {cls.VERSION})")
        return v

    @classmethod
    def upgrade(cls, data: dict) -> dict:
        """``data`` (a JSON object of any version this package wrote) as an object of the
        newest version, by :attr:`UPGRADES` in turn; other objects are returned as they are.
        """
        version = data.get("version") if isinstance(data, dict) else None
        while type(version) is int and version in cls.UPGRADES:
            data = cls.UPGRADES[version](dict(data))
            version = data.get("version")
        return data

    @classmethod
    def checked(cls, data: Any, where: str, fix: str = "") -> "FileSchema":
        """The model of JSON object ``data`` (not upgraded), or :attr:`ERROR` naming ``where``,
        the first field at fault, its value and the fix (``fix``, default :attr:`FIX`).
        """
        if not isinstance(data, dict):
            raise cls.ERROR(f"{where}: not a JSON object; {fix or cls.FIX}")
        version = data.get("version")
        if type(version) is int and version > cls.VERSION:
            raise cls.ERROR(
                f"{where}: its version field is {version}, newer than this package reads (1 to "
                f"{cls.VERSION}); update mitsuba-manifold to read it, or {fix or cls.FIX}"
            )
        try:
            return cls.model_validate(data)
        except ValidationError as e:
            raise cls.ERROR(fault_message(cls, e, where, fix or cls.FIX)) from None


def _short(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _plain(annotation: Any, rule: Any) -> tuple:
    """``(annotation, rule)``: ``annotation`` without ``Optional`` and ``Annotated`` wrappers,
    ``rule`` replaced by a ``description`` given inside ``Annotated[...]``.
    """
    while True:
        origin = typing.get_origin(annotation)
        if origin is typing.Annotated:
            annotation, *meta = typing.get_args(annotation)
            for m in meta:
                rule = getattr(m, "description", None) or rule
        elif origin is typing.Union:
            args = [a for a in typing.get_args(annotation) if a is not type(None)]
            if len(args) != 1:
                return annotation, rule
            annotation = args[0]
        else:
            return annotation, rule


def _rule(model: type, loc: tuple) -> Any:
    """The ``description`` of the field at ``loc`` (keys of objects, indices of lists followed
    through the annotations; an item without one: its container's), or None.
    """
    annotation, rule = model, None
    for part in loc:
        annotation, rule = _plain(annotation, rule)
        if isinstance(annotation, type) and issubclass(annotation, BaseModel):
            fields = {f.alias or n: f for n, f in annotation.model_fields.items()}
            field = fields.get(part) if isinstance(part, str) else None
            if field is None:
                return rule
            rule, annotation = field.description or rule, field.annotation
        elif typing.get_origin(annotation) in (dict, list):
            annotation = typing.get_args(annotation)[-1]
        else:
            return rule
    return _plain(annotation, rule)[1]


def fault_message(model: type, error: ValidationError, where: str, fix: str) -> str:
    """One line of the first fault of ``error``: ``"<where>: its <field> field[ at <entry>]
    must be <rule>, got <value>; <fix>"`` (the rule: the field's ``description``), a missing
    field's ``"... is missing"``, or the words of a validator of the model (a rule between
    fields).
    """
    fault = error.errors(include_url=False)[0]
    loc, kind = tuple(fault["loc"]), fault["type"]
    if kind == "value_error":
        why = str(fault["ctx"]["error"])
    elif kind == "missing":
        why = "is missing"
    else:
        rule = _rule(model, loc)
        said = fault["msg"][:1].lower() + fault["msg"][1:]
        why = f"must be {rule}" if rule else said
        why += f", got {_short(fault['input'])}"
    if not loc:
        return f"{where}: {why}; {fix}"
    at = f" at {'.'.join(map(str, loc[1:]))}" if len(loc) > 1 else ""
    return f"{where}: its {loc[0]} field{at} {why}; {fix}"

"""A record kept in SQLite and served by the API, defined once: a dataclass whose fields carry
their SQLite declaration and their API description.

DESIGN.md's rule — one definition, no copies — for the appliance's own records (the run record,
server/runs/store.py; projects, their builds, versions and run links, projects/store.py). From the
dataclass come:

- the table: ``create_table`` (CREATE TABLE), ``add_missing_columns`` (ALTER TABLE for a field
  marked ``added``, so an older database keeps its rows), ``column_names`` (every SELECT);
- a row read back: ``from_sql`` (JSON text columns decoded, SQLite's 0/1 as bool), and the values
  an UPDATE writes (``to_sql``);
- what the API serves: ``api_model`` (a pydantic model of the served fields, typed and described
  as the dataclass says) and ``served`` (a row's served values). A field marked ``api=False`` is
  stored but never served (a project's folder, a build's paths).

Tests compare the table (PRAGMA table_info) and /openapi.json with the dataclass
(tests/server/test_run_record.py, tests/projects/test_project_record.py).

Importing this module needs the standard library only (pydantic is imported when a model is
made): the build sandbox runs projects/builder.py, which reads the project rows, with a system
Python that has nothing else.
"""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Mapping
from dataclasses import MISSING, Field, dataclass, field, fields
from typing import TYPE_CHECKING, Any, ClassVar, Protocol, TypeVar, cast, get_type_hints

if TYPE_CHECKING:
    from pydantic import BaseModel


class Record(Protocol):
    """A dataclass made of ``column`` fields (what every function here takes)."""

    __dataclass_fields__: ClassVar[dict[str, Field[Any]]]


R = TypeVar("R", bound=Record)


@dataclass(frozen=True)
class Served:
    """A value the API serves beyond a record's columns, computed by the row's ``as_dict()`` (a
    build's ``runnable``): its type and description, declared on the row next to the code that
    makes it."""

    type: Any
    doc: str


def column(
    sql: str, doc: str = "", *, added: bool = False, api: bool = True, json_text: bool = False, **default: Any
) -> Any:
    """A record field: its SQLite declaration (``sql``), its description in the API (``doc``),
    whether it came after the table's first release (``added``: an older database gets it with
    ALTER TABLE, so it needs a default), whether the API serves it (``api``), and whether it is
    stored as JSON text (``json_text``: a dict or list in Python). ``default``: the dataclass
    field's default (``default=`` or ``default_factory=``)."""
    return field(metadata={"sql": sql, "doc": doc, "added": added, "api": api, "json": json_text}, **default)


def column_names(record: type[Record]) -> list[str]:
    """The table's columns, in the dataclass's order (every SELECT lists them so)."""
    return [f.name for f in fields(record)]


def create_table(table: str, record: type[Record], constraints: tuple[str, ...] = ()) -> str:
    """CREATE TABLE IF NOT EXISTS for ``record``; ``constraints``: table constraints after the
    columns (a composite key, a UNIQUE over two columns)."""
    lines = [f"    {f.name} {f.metadata['sql']}" for f in fields(record)]
    lines += [f"    {c}" for c in constraints]
    return f"CREATE TABLE IF NOT EXISTS {table} (\n" + ",\n".join(lines) + "\n);\n"


def add_missing_columns(db: sqlite3.Connection, table: str, record: type[Record]) -> None:
    """Give a table an older release made the fields added since (marked ``added``)."""
    have = {r[1] for r in db.execute(f"PRAGMA table_info({table})")}
    for f in fields(record):
        if f.name not in have and f.metadata["added"]:
            db.execute(f"ALTER TABLE {table} ADD COLUMN {f.name} {f.metadata['sql']}")


def from_sql(record: type[R], values: tuple[Any, ...]) -> R:
    """A ``record`` from one row SELECTed in ``column_names`` order: JSON columns decoded (empty
    text as the field's default), INTEGER 0/1 as bool where the field is a bool."""
    hints = get_type_hints(record)
    kwargs: dict[str, Any] = {}
    for f, value in zip(fields(record), values):
        if f.metadata["json"]:
            value = json.loads(value) if value else _default(f)
        elif hints[f.name] is bool:
            value = bool(value)
        kwargs[f.name] = value
    row: R = cast(Any, record)(**kwargs)
    return row


def to_sql(record: type[Record], values: dict[str, Any]) -> dict[str, Any]:
    """Column values for an INSERT or UPDATE: JSON columns encoded. A name that is not a column
    is a KeyError (a typo must not become silent SQL)."""
    by_name = {f.name: f for f in fields(record)}
    unknown = set(values) - set(by_name)
    if unknown:
        raise KeyError(sorted(unknown))
    return {k: json.dumps(v) if by_name[k].metadata["json"] else v for k, v in values.items()}


def served(row: Record) -> dict[str, Any]:
    """The row's served fields (not those marked ``api=False``), by name."""
    return {f.name: getattr(row, f.name) for f in fields(row) if f.metadata["api"]}


def api_model(
    record: type[Record],
    name: str,
    extra: Mapping[str, tuple[Any, Any] | Served] | None = None,
    exclude: frozenset[str] = frozenset(),
) -> type[BaseModel]:
    """The API model of ``record``: its served fields in order (but ``exclude``: what one answer
    leaves out), typed and described as the dataclass says, then ``extra`` (name -> (type,
    pydantic Field), or a Served): what the answer adds. An extra named like a field the API does
    not serve takes that field's place (a version's ``files``: stored as the file table, served as
    its size)."""
    from pydantic import Field as ApiField
    from pydantic import create_model

    hints = get_type_hints(record)
    added = {k: (v.type, ApiField(description=v.doc)) if isinstance(v, Served) else v for k, v in (extra or {}).items()}
    spec: dict[str, Any] = {}
    for f in fields(record):
        if f.name in added:
            spec[f.name] = added.pop(f.name)
        elif f.metadata["api"] and f.name not in exclude:
            doc = f.metadata["doc"] or None
            if f.default is not MISSING:
                spec[f.name] = (hints[f.name], ApiField(default=f.default, description=doc))
            else:
                spec[f.name] = (hints[f.name], ApiField(description=doc))
    spec.update(added)
    return create_model(name, **spec)


def list_of(model: type[BaseModel]) -> object:
    """``list[model]`` for a response model or a field: a model made at import is a value to a
    type checker, not a type, so it cannot be written ``list[model]`` where one is checked."""
    return cast(Any, list)[model]


def _default(f: Field[Any]) -> Any:
    if f.default_factory is not MISSING:
        return f.default_factory()
    if f.default is not MISSING:
        return f.default
    raise ValueError(f"{f.name}: empty JSON text and no default")

"""``PlantName``: a request field that names a simulated plant of rt_core's plant table.

A ``Literal`` would be a second list of plants; this is a string checked against the table the
sim board indexes (``xrflab.plants``, read through the cffi binding), whose JSON Schema still
lists the choices (an ``enum`` in /openapi.json, as the Literal gave).

Beside the plant table, not among the routes that use it (server/http/runs.py, projects.py): a
route module is imported by the app only (tests/lint/layers.py).
"""

from __future__ import annotations

from typing import Annotated

from pydantic import AfterValidator, BaseModel, Field, WithJsonSchema

from . import plants

PlantName = Annotated[
    str,
    AfterValidator(plants.check_name),
    WithJsonSchema({"type": "string", "enum": list(plants.names())}),
]


class PlantInfo(BaseModel):
    """One row of the plant table (GET /api/plants)."""

    id: int = Field(description="the plant's id in rt_core's plant table (XRF_SIM by number)")
    name: str = Field(description="XRF_SIM=<name>; the bench profile and example of the same name")
    title: str
    axes: int = Field(description="motor channels wired, 1..axes")
    state: list[str] = Field(description="the simulated plant's state values as 'name unit'")
    channels: int = Field(description="the bench's channel count, 1..XRF_MAX_CHANNELS (ico boards of four)")

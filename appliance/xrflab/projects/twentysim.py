"""What the build page shows of a 20-sim controller: step size, integration method, inputs, outputs.

20-sim's C++ code generation writes, next to the submodel's class:
- ``<Submodel>_tokens.xml``: ``<token name="...">value</token>`` for SUBMODEL_NAME,
  TIME_STEP_SIZE, INTEGRATION_METHOD_NAME, START/FINISH_TIME, NUMBER_INPUTS/OUTPUTS, … and,
  with newer templates, INPUT_NAMES / OUTPUT_NAMES (or *_VARIABLE_NAMES);
- ``<Submodel>.info``: a text summary with ``Inputs (u):`` / ``Outputs (y):`` tables
  (index, name, unit).
Both are read as text with regular expressions: no XML parser (no entities, nothing resolved),
and a file over 1 MB is not read at all.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

# The one reading of a tokens file (installed for builds too: the parameter table).
from ..twentysim_params import parameters, parse_tokens

MAX_BYTES = 1 << 20
_SECTION_RE = re.compile(r"^\s*(Inputs|Outputs)\b[^\n]*:\s*$", re.M | re.I)
_ROW_RE = re.compile(r"^\s*(\d+)\s+([A-Za-z_][\w.\[\]]*)\s*(.*?)\s*$")


def _read(path: Path) -> str:
    if not path.is_file() or path.is_symlink() or path.stat().st_size > MAX_BYTES:
        return ""
    return path.read_text(errors="replace")


def parse_info(text: str) -> dict[str, list[dict[str, str]]]:
    out: dict[str, list[dict[str, str]]] = {"inputs": [], "outputs": []}
    heads = list(_SECTION_RE.finditer(text))
    for i, h in enumerate(heads):
        end = heads[i + 1].start() if i + 1 < len(heads) else len(text)
        key = "inputs" if h.group(1).lower() == "inputs" else "outputs"
        for line in text[h.end() : end].splitlines():
            if not line.strip():
                if out[key]:
                    break
                continue
            m = _ROW_RE.match(line)
            if not m:
                break
            out[key].append({"index": m.group(1), "name": m.group(2), "unit": m.group(3)})
    return out


def _names(tokens: dict[str, str], *keys: str) -> list[str]:
    for k in keys:
        v = tokens.get(k)
        if v:
            return [n for n in re.split(r"[\s,;]+", v) if n]
    return []


def find_controller(project: Path) -> Path | None:
    c = project / "controller"
    return c if c.is_dir() and not c.is_symlink() and any(c.glob("*_tokens.xml")) else None


def describe(project: Path) -> dict[str, Any] | None:
    """The 20-sim facts of a project, or None when it has no controller/ with a tokens file."""
    folder = find_controller(project)
    if folder is None:
        return None
    tokens_files = sorted(folder.glob("*_tokens.xml"))
    tokens_file = tokens_files[0]
    tokens = parse_tokens(_read(tokens_file))
    submodel = tokens.get("SUBMODEL_NAME") or tokens_file.name[: -len("_tokens.xml")]
    info_file = folder / f"{submodel}.info"
    info = parse_info(_read(info_file)) if info_file.exists() else {"inputs": [], "outputs": []}
    step_raw = tokens.get("TIME_STEP_SIZE", "")
    try:
        step = float(step_raw)
        freq = round(1.0 / step, 6) if step > 0 else None
    except ValueError:
        step, freq = None, None
    inputs = [r["name"] for r in info["inputs"]] or _names(tokens, "INPUT_NAMES", "INPUT_VARIABLE_NAMES")
    outputs = [r["name"] for r in info["outputs"]] or _names(tokens, "OUTPUT_NAMES", "OUTPUT_VARIABLE_NAMES")
    params, param_problems = parameters(tokens)
    problems = []
    if step is None:
        problems.append(f"{tokens_file.name}: no usable TIME_STEP_SIZE ({step_raw or 'missing'})")
    return {
        "folder": "controller",
        "tokens_file": f"controller/{tokens_file.name}",
        "info_file": f"controller/{info_file.name}" if info_file.exists() else "",
        "submodel": submodel,
        "model": tokens.get("MODEL_NAME", ""),
        "time_step_size": step,
        "frequency_hz": freq,
        "integration_method": tokens.get("INTEGRATION_METHOD_NAME", ""),
        "start_time": tokens.get("START_TIME", ""),
        "finish_time": tokens.get("FINISH_TIME", ""),
        "inputs": inputs,
        "outputs": outputs,
        "input_units": {r["name"]: r["unit"] for r in info["inputs"]},
        "output_units": {r["name"]: r["unit"] for r in info["outputs"]},
        "number_inputs": tokens.get("NUMBER_INPUTS", ""),
        "number_outputs": tokens.get("NUMBER_OUTPUTS", ""),
        "parameters": [{"index": p.index, "name": p.name, "default": p.default, "unit": p.unit} for p in params],
        "problems": problems + param_problems,
    }

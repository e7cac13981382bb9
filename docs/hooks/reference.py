"""The reference pages that must not drift, generated from the code at build time.

- `reference/cli.md`: every verb of `cellctl`, from the argparse parser (cellctl.cli.build_parser);
- `reference/http-api.md`: every route of the daemon, from its OpenAPI schema (cellctl.http.api.create_app on a
  daemon of the simulated micro cell, built in a temporary folder and never started);
- `reference/cell-file.md`: every key of the cell file, from the pydantic models (cellctl.config.CellFile, each
  driver's `Settings`, each simulated world's `sim:` model, each routine's `Params`).

As an MkDocs hook (mkdocs.yml `hooks:`), `on_files` adds them to the site as generated files: nothing is written
into docs/. Run as a script, `python docs/hooks/reference.py OUT_DIR` writes them to OUT_DIR to read or diff.
"""

from __future__ import annotations

import argparse
import inspect
import json
import os
import re
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PAGES = ("reference/cli.md", "reference/http-api.md", "reference/cell-file.md")
WIDTH = 100


# -- shared ------------------------------------------------------------------------------------------------------


def _plain(text) -> str:
    """One line, pipes escaped (a table cell's)."""
    if text is None:
        return ""
    return " ".join(str(text).split()).replace("|", "\\|")


def _prose(text) -> str:
    """Text as Markdown prose: <store> and the like kept as text, not taken for HTML tags (outside `code`)."""
    parts = re.split(r"(`[^`]*`)", str(text))
    return "".join(part if part.startswith("`") else part.replace("<", "&lt;").replace(">", "&gt;")
                   for part in parts)


def _cell(text) -> str:
    """Prose for one table cell."""
    return _prose(_plain(text))


def _code(text) -> str:
    text = _plain(text)
    return f"`{text}`" if text else ""


def _table(head: tuple[str, ...], rows: list[tuple]) -> list[str]:
    if not rows:
        return []
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    out += ["| " + " | ".join(_cell(c) if not str(c).startswith("`") else str(c) for c in row) + " |"
            for row in rows]
    return out + [""]


GENERATED = ("!!! note \"Generated\"\n    This page is generated from the code each time the site is built "
             "(`docs/hooks/reference.py`); it cannot drift from it. Do not edit it by hand.\n")


# -- the command line --------------------------------------------------------------------------------------------


def _subparsers(parser: argparse.ArgumentParser):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help for a in action._choices_actions}
            for name, sub in action.choices.items():
                yield name, sub, helps.get(name)


def _option_rows(parser: argparse.ArgumentParser) -> list[tuple]:
    rows = []
    for action in parser._actions:
        if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
            continue
        if action.option_strings:
            name = ", ".join(action.option_strings)
            if action.nargs != 0:
                metavar = action.metavar or action.dest.upper()
                if isinstance(metavar, tuple):
                    metavar = " ".join(metavar)
                name += f" {metavar}"
        else:
            name = action.metavar or action.dest
            if isinstance(name, tuple):
                name = " ".join(name)
        helptext = action.help if action.help not in (None, argparse.SUPPRESS) else ""
        if "%(" in helptext:
            try:
                helptext = helptext % {**vars(action), "prog": parser.prog}
            except (KeyError, TypeError, ValueError):
                pass
        if action.choices is not None and not isinstance(action.choices, dict):
            if not all(str(choice) in helptext for choice in action.choices):
                helptext += " (one of: " + ", ".join(map(str, action.choices)) + ")"
        default = action.default
        shown = "" if default in (None, False, argparse.SUPPRESS, []) or action.nargs == 0 else _code(default)
        rows.append((_code(name), helptext, shown, "yes" if action.required else ""))
    return rows


def _verb_section(path: list[str], parser: argparse.ArgumentParser, helptext: str | None, level: int) -> list[str]:
    title = " ".join(path)
    out = [f"{'#' * level} `{title}`", ""]
    if helptext:
        out += [_prose(helptext[0].upper() + helptext[1:] + ("" if helptext.endswith(".") else ".")), ""]
    if parser.description and parser.description != helptext:
        out += [_prose(parser.description), ""]
    usage = parser.format_usage().strip()
    out += ["```text", usage, "```", ""]
    out += _table(("argument", "meaning", "default", "required"), _option_rows(parser))
    if parser.epilog:
        out += [_prose(parser.epilog), ""]
    for name, sub, subhelp in _subparsers(parser):
        out += _verb_section([*path, name], sub, subhelp, min(level + 1, 4))
    return out


def cli_page() -> str:
    os.environ["COLUMNS"] = str(WIDTH)  # argparse wraps its usage at the terminal's width
    from cellctl.cli import build_parser

    parser = build_parser()
    verbs = list(_subparsers(parser))
    out = ["# Command line (`cellctl`)", "", GENERATED,
           "The command line reaches the cell in one of two ways: in this process on the cell file's store "
           "(`--config`), or through the daemon (`--url` / `$CELLCTL_URL`, the token from `--token` / "
           "`$CELLCTL_TOKEN` or the store's token file): [run jobs through the daemon](../how-to/daemon.md) says which "
           "verbs take which way; the exit statuses are below.", "",
           "```text", parser.format_help().strip(), "```", "",
           "| verb | what it does |", "|---|---|"]
    out += [f"| [`{name}`](#cellctl-{name}) | {_cell(h)} |" for name, _, h in verbs]
    out += ["", "## Exit status", "",
            "| status | meaning |", "|---|---|",
            "| 0 | done |",
            "| 1 | the cell failed: a device fault (the message names it), a job that faulted, a daemon that "
            "cannot be reached |",
            "| 2 | bad input or refused: a cell file, argument or samples file that is wrong (the message names "
            "the key, row or column and what is allowed), a request the cell refused, a cell another process "
            "owns, a port in use |",
            "| 130 | interrupted: every sample so far is kept (`--resume` continues from them), or the job "
            "was paused or aborted |", "", "## Verbs", ""]
    for name, sub, helptext in verbs:
        out += _verb_section(["cellctl", name], sub, helptext, 3)
    return "\n".join(out) + "\n"


# -- the HTTP API ------------------------------------------------------------------------------------------------


@contextmanager
def _no_env(*names: str):
    saved = {n: os.environ.pop(n) for n in names if n in os.environ}
    try:
        yield
    finally:
        os.environ.update(saved)


def openapi_schema() -> dict:
    """The daemon's /openapi.json, from a daemon of the simulated micro cell that is built but never started."""
    import yaml

    from cellctl.http.api import create_app
    from cellctl.startup.daemon import Daemon

    with tempfile.TemporaryDirectory(prefix="cellctl-docs-") as tmp, _no_env("CELLCTL_STORE"):
        data = yaml.safe_load((ROOT / "config" / "sim-microcell.yaml").read_text())
        data["store_dir"] = str(Path(tmp) / "store")
        cell_file = Path(tmp) / "cell.yaml"
        cell_file.write_text(yaml.safe_dump(data))
        daemon = Daemon(cell_file)
        try:
            return create_app(daemon).openapi()
        finally:
            daemon.jobs.close()
            daemon.calstore.close()


def _schema_type(schema: dict, defs: dict | None = None) -> str:
    if not schema:
        return "any"
    if "$ref" in schema:
        name = schema["$ref"].rsplit("/", 1)[-1]
        return f"[{name}](#{name.lower()})" if defs is not None and name in defs else name
    for key in ("anyOf", "oneOf"):
        if key in schema:
            return " or ".join(_schema_type(s, defs) for s in schema[key])
    if "allOf" in schema and len(schema["allOf"]) == 1:
        return _schema_type(schema["allOf"][0], defs)
    if "enum" in schema:
        return "one of " + ", ".join(f"`{v}`" for v in schema["enum"])
    if "const" in schema:
        return f"`{json.dumps(schema['const'])}`"
    kind = schema.get("type", "any")
    if kind == "array":
        if "prefixItems" in schema:
            return "[" + ", ".join(_schema_type(s, defs) for s in schema["prefixItems"]) + "]"
        return f"list of {_schema_type(schema.get('items', {}), defs)}"
    if kind == "object" and isinstance(schema.get("additionalProperties"), dict):
        return f"mapping of name to {_schema_type(schema['additionalProperties'], defs)}"
    return str(kind)


def _limits(schema: dict) -> str:
    parts = []
    if schema.get("minItems") is not None and schema.get("minItems") == schema.get("maxItems"):
        parts.append(f"{schema['minItems']} items")
        schema = {k: v for k, v in schema.items() if k not in ("minItems", "maxItems")}
    for key, word in (("minimum", "≥"), ("exclusiveMinimum", ">"), ("maximum", "≤"), ("exclusiveMaximum", "<"),
                      ("minLength", "length ≥"), ("maxLength", "length ≤"), ("minItems", "items ≥"),
                      ("maxItems", "items ≤"), ("pattern", "matches")):
        if key in schema:
            value = schema[key]
            if isinstance(value, float) and value.is_integer():
                value = int(value)  # 4294967295, not 4294967295.0
            parts.append(f"{word} `{value}`" if key == "pattern" else f"{word} {value}")
    for sub in schema.get("anyOf", []):
        inner = _limits(sub)
        if inner:
            parts.append(inner)
    return ", ".join(parts)


def _default(schema: dict) -> str:
    return _code(json.dumps(schema["default"], ensure_ascii=False)) if "default" in schema else ""


def http_page() -> str:
    schema = openapi_schema()
    defs = schema.get("components", {}).get("schemas", {})
    info = schema.get("info", {})
    out = ["# HTTP API", "", GENERATED,
           f"{info.get('title', 'the daemon')}, API version {info.get('version', '?')} (OpenAPI "
           f"{schema.get('openapi', '?')}). A running daemon serves the same schema at `/openapi.json`. "
           "Every request that changes the cell needs `Authorization: Bearer TOKEN` (`cellctl token` prints "
           "it); while another client holds the operator lock it is refused with 423, and the lock's holder "
           "sends its lock id in `X-Cellctl-Lock` ([the operator lock](../how-to/stale-lock.md)). "
           "Reads (`GET`) need no token.", "",
           "| method | path | what it does |", "|---|---|---|"]
    ops = [(path, method, op) for path, item in schema["paths"].items() for method, op in item.items()
           if method in ("get", "post", "put", "patch", "delete")]
    anchors = {}
    for path, method, op in ops:
        anchor = f"{method}-{path}".lower().replace("/", "-").replace("{", "").replace("}", "").replace("_", "-")
        anchor = "-".join(p for p in anchor.split("-") if p)
        anchors[(path, method)] = anchor
        out.append(f"| {method.upper()} | [`{path}`](#{anchor}) | {_cell(op.get('summary'))} |")
    out += ["", "## Routes", ""]
    for path, method, op in ops:
        out += [f"### {method.upper()} `{path}` {{#{anchors[(path, method)]}}}", ""]
        if op.get("summary"):
            out += [_prose(op["summary"][0].upper() + op["summary"][1:] + "."), ""]
        if op.get("description"):
            out += [_prose(op["description"].strip()), ""]
        params = [(_code(p["name"]), p.get("in", ""), _schema_type(p.get("schema", {}), defs),
                   "yes" if p.get("required") else "", _default(p.get("schema", {})), _limits(p.get("schema", {})),
                   p.get("description") or p.get("schema", {}).get("description", ""))
                  for p in op.get("parameters", [])]
        if params:
            out += ["Parameters:", ""]
            out += _table(("name", "in", "type", "required", "default", "limits", "meaning"), params)
        body = op.get("requestBody")
        if body:
            content = body.get("content", {})
            kinds = ", ".join(f"{ctype}: {_schema_type(c.get('schema', {}), defs)}" for ctype, c in content.items())
            out += [f"Request body ({'required' if body.get('required') else 'optional'}): {kinds}", ""]
        responses = [(_code(code), r.get("description", ""),
                      ", ".join(f"{ctype}" + (f": {_schema_type(c['schema'], defs)}" if c.get("schema") else "")
                                for ctype, c in r.get("content", {}).items()))
                     for code, r in op.get("responses", {}).items()]
        out += ["Answers:", ""]
        out += _table(("status", "meaning", "content"), responses)
    if defs:
        out += ["## Schemas", "", "The request and answer bodies the routes name.", ""]
        for name, model in defs.items():
            out += [f"### {name} {{#{name.lower()}}}", ""]
            if model.get("description"):
                out += [_prose(model["description"].strip()), ""]
            required = set(model.get("required", []))
            rows = [(_code(key), _schema_type(prop, defs), "yes" if key in required else "", _default(prop),
                     _limits(prop), prop.get("description", ""))
                    for key, prop in model.get("properties", {}).items()]
            out += _table(("field", "type", "required", "default", "limits", "meaning"), rows)
            if model.get("additionalProperties") is False:
                out += ["Any other field is refused (422).", ""]
    return "\n".join(out) + "\n"


# -- the cell file -----------------------------------------------------------------------------------------------


def _resolve(schema: dict, defs: dict) -> dict:
    while "$ref" in schema:
        schema = defs[schema["$ref"].rsplit("/", 1)[-1]]
    if "allOf" in schema and len(schema["allOf"]) == 1:
        return _resolve(schema["allOf"][0], defs)
    return schema


def _nested(schema: dict, defs: dict) -> tuple[str, dict] | None:
    """("", model) for a nested object, (".NAME", model) for a mapping of names to objects; else None."""
    schema = _resolve(schema, defs)
    options = [s for s in schema.get("anyOf", []) if s.get("type") != "null"]
    if len(options) == 1:
        return _nested(options[0], defs)
    if "properties" in schema:
        return "", schema
    extra = schema.get("additionalProperties")
    if schema.get("type") == "object" and isinstance(extra, dict):
        inner = _resolve(extra, defs)
        if "properties" in inner:
            return ".NAME", inner
    return None


def _key_rows(schema: dict, defs: dict, prefix: str, skip: set[str] = frozenset()) -> list[tuple]:
    rows = []
    required = set(schema.get("required", []))
    for key, prop in schema.get("properties", {}).items():
        path = f"{prefix}{key}"
        if path in skip:
            continue
        described = prop.get("description") or _resolve(prop, defs).get("description", "")
        nested = _nested(prop, defs)
        kind = "section" if nested is not None and nested[0] == "" else (
            "mapping: name → section" if nested is not None else _schema_type(prop))
        default = "" if kind == "section" else _default(prop)  # a section's keys are listed below it
        rows.append((_code(path), kind, "yes" if key in required else "", default, _limits(prop),
                     " ".join(str(described).split()[:80])))
        if nested is not None:
            rows += _key_rows(nested[1], defs, f"{path}{nested[0]}.", skip)
    return rows


def _model_rows(model, prefix: str = "", skip: set[str] = frozenset()) -> list[tuple]:
    schema = model.model_json_schema()
    return _key_rows(schema, schema.get("$defs", {}), prefix, skip)


KEY_HEAD = ("key", "type", "required", "default", "limits", "meaning")


def cell_file_page() -> str:
    from drivers.registry import BACKENDS, backend_class
    from drivers.sim import kinds

    from calibration.routines import routine_class, routine_names

    from cellctl.config import CellFile

    out = ["# Cell file keys", "", GENERATED,
           "A cell file is YAML, checked by `cellctl check --config FILE` before anything connects: an unknown "
           "key, a value of the wrong type or out of its range is an error that names the key and what is "
           "allowed. [Write a cell file](../how-to/cell-file.md) walks through one.", "",
           "## Top-level keys", ""]
    out += _table(KEY_HEAD, _model_rows(CellFile, skip={"sim"}))
    out += ["`arm`, `gripper`, `operator` and each of `cameras` are a device: `backend` picks its driver, and "
            "every other key is that driver's option, listed below per backend. `sim` is the simulated world "
            "(below, per kind of world); `routines` holds default parameters per routine (below, per routine).",
            "", "## Devices", ""]
    for kind in ("arm", "gripper", "camera", "operator"):
        out += [f"### {kind.capitalize()} backends", ""]
        for backend, target in sorted(BACKENDS.get(kind, {}).items()):
            out += [f"#### `{kind}: {{backend: {backend}}}` {{#{kind}-{backend}}}", "", f"Driver: `{target}`.", ""]
            try:
                settings = backend_class(kind, backend).Settings
            except Exception as exc:  # noqa: BLE001 - a vendor SDK missing here: the page says so, the build goes on
                out += [f"Its options could not be read here ({_cell(exc)}).", ""]
                continue
            doc = inspect.cleandoc(settings.__doc__ or "")
            if doc and not doc.startswith("Usage docs"):
                out += [_prose(" ".join(paragraph.split())) + "\n" for paragraph in doc.split("\n\n")]
            rows = _model_rows(settings)
            out += _table(KEY_HEAD, rows) if rows else ["No options besides `backend`.", ""]
    out += ["## The simulated world (`sim:`)", "",
            "Only in a simulated cell file. `sim.world` picks the kind of world (default `micro-cell`); each "
            "kind has its own keys and its own fakes (the `backend` of each device).", ""]
    for name, kind in kinds.WORLD_KINDS.items():
        fakes = ", ".join(f"{dev}: `{fake.backend}`" for dev, fake in kind.fakes.items())
        out += [f"### `sim: {{world: {name}}}` {{#sim-{name}}}", "", f"Fakes: {fakes}.", ""]
        out += _table(KEY_HEAD, _model_rows(kind.config, prefix="sim."))
    out += ["## Routine parameters (`routines:`)", "",
            "`routines.NAME` sets a routine's default parameters (`--param KEY=VALUE` overrides one for a run); "
            "`routines.NAME.AREA` sets them for one area only, applied when the routine runs with `area=AREA`.", ""]
    for name in routine_names():
        try:
            params = routine_class(name).Params
        except Exception as exc:  # noqa: BLE001 - as above
            out += [f"### `{name}`", "", f"Its parameters could not be read here ({_cell(exc)}).", ""]
            continue
        doc = (routine_class(name).__doc__ or "").strip().split("\n\n")[0]
        out += [f"### `{name}` {{#routine-{name}}}", ""]
        if doc:
            out += [_prose(" ".join(doc.split())), ""]
        rows = _model_rows(params, prefix=f"routines.{name}.")
        out += _table(KEY_HEAD, rows) if rows else ["No parameters.", ""]
    return "\n".join(out) + "\n"


# -- MkDocs ------------------------------------------------------------------------------------------------------


def pages() -> dict[str, str]:
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    return {"reference/cli.md": cli_page(), "reference/http-api.md": http_page(),
            "reference/cell-file.md": cell_file_page()}


def on_files(files, config):
    """MkDocs hook: the generated pages join the site's files (a file of that name in docs/ is replaced)."""
    from mkdocs.structure.files import File

    for uri, text in pages().items():
        existing = files.get_file_from_path(uri)
        if existing is not None:
            files.remove(existing)
        files.append(File.generated(config, uri, content=text))
    return files


if __name__ == "__main__":
    target = Path(sys.argv[1] if len(sys.argv) > 1 else ROOT / "build" / "docs-reference")
    for uri, text in pages().items():
        path = target / uri
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        print(path)

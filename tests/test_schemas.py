"""The committed schemas/ files match the models, and examples validate against both.

Clients in other languages validate against the files, not the pydantic models, so the
examples are checked with a small JSON Schema (2020-12) validator written here for the
keywords pydantic emits; it refuses any keyword it does not know rather than skip it.
If the ``jsonschema`` package happens to be installed it is used as well.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest

from services import messages as m
from services.schemas import COUNTER_EXAMPLES, EXAMPLES, SCHEMA_DIR, SCHEMAS, schema_for

ANNOTATIONS = {"$schema", "$id", "title", "description", "default", "discriminator", "examples", "$defs"}


class SchemaError(AssertionError):
    pass


def _type_ok(value: Any, t: str) -> bool:
    if t == "object":
        return isinstance(value, dict)
    if t == "array":
        return isinstance(value, list)
    if t == "string":
        return isinstance(value, str)
    if t == "boolean":
        return isinstance(value, bool)
    if t == "null":
        return value is None
    if t == "integer":
        return isinstance(value, int) and not isinstance(value, bool) or (
            isinstance(value, float) and value.is_integer()
        )
    if t == "number":
        return isinstance(value, int | float) and not isinstance(value, bool)
    raise SchemaError(f"unknown type {t!r}")


def validate(value: Any, schema: dict[str, Any], root: dict[str, Any], path: str = "$") -> None:
    """Raise SchemaError if ``value`` does not satisfy ``schema`` (a subset of 2020-12)."""
    for key, s in schema.items():
        if key in ANNOTATIONS or key.startswith("x-"):
            continue
        if key == "$ref":
            assert s.startswith("#/$defs/"), s
            validate(value, root["$defs"][s[len("#/$defs/") :]], root, path)
        elif key == "type":
            types = s if isinstance(s, list) else [s]
            if not any(_type_ok(value, t) for t in types):
                raise SchemaError(f"{path}: {value!r} is not of type {s}")
        elif key == "const":
            if value != s or type(value) is bool and type(s) is not bool:
                raise SchemaError(f"{path}: {value!r} != const {s!r}")
        elif key == "enum":
            if value not in s:
                raise SchemaError(f"{path}: {value!r} not in {s}")
        elif key in ("minimum", "maximum", "exclusiveMinimum", "exclusiveMaximum"):
            if _type_ok(value, "number"):
                bad = {
                    "minimum": value < s,
                    "maximum": value > s,
                    "exclusiveMinimum": value <= s,
                    "exclusiveMaximum": value >= s,
                }[key]
                if bad:
                    raise SchemaError(f"{path}: {value} violates {key} {s}")
        elif key in ("minLength", "maxLength"):
            if isinstance(value, str) and (len(value) < s if key == "minLength" else len(value) > s):
                raise SchemaError(f"{path}: length violates {key} {s}")
        elif key in ("minItems", "maxItems"):
            if isinstance(value, list) and (len(value) < s if key == "minItems" else len(value) > s):
                raise SchemaError(f"{path}: {len(value)} items violates {key} {s}")
        elif key == "prefixItems":
            if isinstance(value, list):
                for i, (v, sub) in enumerate(zip(value, s, strict=False)):
                    validate(v, sub, root, f"{path}[{i}]")
        elif key == "items":
            if isinstance(value, list):
                start = len(schema.get("prefixItems", []))
                for i, v in enumerate(value[start:], start):
                    validate(v, s, root, f"{path}[{i}]")
        elif key == "properties":
            if isinstance(value, dict):
                for name, sub in s.items():
                    if name in value:
                        validate(value[name], sub, root, f"{path}.{name}")
        elif key == "required":
            if isinstance(value, dict):
                missing = [r for r in s if r not in value]
                if missing:
                    raise SchemaError(f"{path}: missing {missing}")
        elif key == "additionalProperties":
            if isinstance(value, dict):
                extra = [k for k in value if k not in schema.get("properties", {})]
                if s is False and extra:
                    raise SchemaError(f"{path}: additional properties {extra}")
                if isinstance(s, dict):
                    for k in extra:
                        validate(value[k], s, root, f"{path}.{k}")
        elif key in ("anyOf", "oneOf"):
            passed = 0
            for sub in s:
                try:
                    validate(value, sub, root, path)
                    passed += 1
                except SchemaError:
                    pass
            if passed == 0 or (key == "oneOf" and passed > 1):
                raise SchemaError(f"{path}: {passed} of the {key} alternatives match")
        elif key == "allOf":
            for sub in s:
                validate(value, sub, root, path)
        else:
            raise SchemaError(f"the test validator does not know keyword {key!r}: extend it")


def _committed(name: str) -> dict[str, Any]:
    path = SCHEMA_DIR / f"{name}.json"
    assert path.is_file(), f"{path} missing: run `python -m services.schemas`"
    return json.loads(path.read_text(encoding="utf-8"))


@pytest.mark.parametrize("name", sorted(SCHEMAS))
def test_committed_schema_matches_the_models(name):
    assert _committed(name) == schema_for(name), (
        f"schemas/{name}.json drifted from services.messages: run `python -m services.schemas` "
        "(and bump messages.PROTOCOL_VERSION if the change is not backward compatible)"
    )


def test_no_stray_schema_files():
    files = {p.stem for p in Path(SCHEMA_DIR).glob("*.json")}
    assert files == set(SCHEMAS)


@pytest.mark.parametrize("name", sorted(SCHEMAS))
def test_schema_header_names_dialect_and_version(name):
    s = _committed(name)
    assert s["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    assert s["$id"] == f"urn:lino-loc:schema:{name}:v{m.PROTOCOL_VERSION}"
    assert s["x-protocol-version"] == m.PROTOCOL_VERSION


def _model_accepts(name: str, payload: dict[str, Any]) -> bool:
    raw = json.dumps(payload)
    if name == "request":
        return not isinstance(m.parse_request(raw.encode()), m.ErrorReply)
    if name == "reply":
        try:
            m.parse_reply(raw)
            return True
        except ValueError:
            return False
    try:
        m.TOPICS[name].model_validate_json(raw)
        return True
    except ValueError:
        return False


@pytest.mark.parametrize("name", sorted(SCHEMAS))
def test_examples_validate_against_model_and_committed_schema(name):
    schema = _committed(name)
    assert EXAMPLES[name], f"no example for {name}"
    for payload in EXAMPLES[name]:
        assert _model_accepts(name, payload), payload
        validate(payload, schema, schema)


@pytest.mark.parametrize("name", sorted(COUNTER_EXAMPLES))
def test_counter_examples_refused_by_model_and_schema(name):
    schema = _committed(name)
    for payload, why in COUNTER_EXAMPLES[name]:
        assert not _model_accepts(name, payload), why
        with pytest.raises(SchemaError):
            validate(payload, schema, schema)


@pytest.mark.parametrize("topic", sorted(m.TOPICS))
def test_what_the_daemon_sends_validates_against_the_schema(topic):
    """Serialization schemas: a model's own JSON output (all fields present) validates."""
    model = m.TOPICS[topic].model_validate(EXAMPLES[topic][0])
    out = json.loads(model.model_dump_json())
    schema = _committed(topic)
    validate(out, schema, schema)
    # ... and a message missing a field the daemon always sends does not
    out.pop("v")
    with pytest.raises(SchemaError, match="missing"):
        validate(out, schema, schema)


def test_validator_is_not_vacuous():
    schema = _committed("pose")
    bad = {**EXAMPLES["pose"][0], "pose": {"x": 1.0, "y": "north", "theta": 0.0}}
    with pytest.raises(SchemaError, match="y"):
        validate(bad, schema, schema)
    with pytest.raises(SchemaError, match="does not know"):
        validate(1, {"patternProperties": {}}, {})
    assert math.isfinite(EXAMPLES["pose"][0]["stamp"])


def test_with_jsonschema_if_installed():
    jsonschema = pytest.importorskip("jsonschema", reason="optional: the jsonschema package is not installed")
    for name in SCHEMAS:
        schema = _committed(name)
        jsonschema.Draft202012Validator.check_schema(schema)
        v = jsonschema.Draft202012Validator(schema)
        for payload in EXAMPLES[name]:
            v.validate(payload)
        for payload, _ in COUNTER_EXAMPLES.get(name, []):
            assert not v.is_valid(payload)


DOC = Path(__file__).resolve().parents[1] / "docs" / "zeromq.md"


def test_docs_examples_validate():
    """Every ```json block of docs/zeromq.md is marked with its schema and validates."""
    import re

    text = DOC.read_text(encoding="utf-8")
    blocks = re.findall(r"(<!-- (example|examples): (\w+) -->\n)?```json\n(.*?)```", text, re.S)
    assert len(blocks) >= 6
    for marker, kind, name, body in blocks:
        assert marker, f"unmarked json block in {DOC.name}: {body[:60]!r}"
        payloads = [json.loads(body)] if kind == "example" else [json.loads(x) for x in body.splitlines() if x.strip()]
        schema = _committed(name)
        for payload in payloads:
            assert _model_accepts(name, payload), payload
            validate(payload, schema, schema)


def test_docs_python_snippets_compile():
    import ast
    import re

    snippets = re.findall(r"```python\n(.*?)```", DOC.read_text(encoding="utf-8"), re.S)
    assert snippets
    for code in snippets:
        ast.parse(code)
    subscriber = snippets[0].strip().splitlines()
    assert len(subscriber) <= 10  # "a ten-line Python subscriber"

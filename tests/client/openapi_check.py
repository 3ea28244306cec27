#!/usr/bin/env python3
"""Validates proto/openapi.yaml against itself and against what the server really answers.

  openapi_check.py OPENAPI.yaml [CAPTURES.json]

1. Every `example` of a schema, and every media-type `example` of a request body or response,
   validates against its schema (JSON Schema 2020-12, the dialect of OpenAPI 3.1).
2. Every captured answer (a JSON list of {"method", "route", "status", "content_type", "body"},
   written by tests/client/openapi_test.cpp from a live kdrt-server) is documented: the route and
   method exist, the status is listed, the media type is listed under it, and a JSON body
   validates against that schema.

Prints one line per problem and exits 1 if there is any. Needs python3-yaml and
python3-jsonschema (scripts/deps.sh installs them).
"""

import json
import sys

try:
    import jsonschema
    import yaml
except ImportError as error:  # pragma: no cover - reported to the C++ test
    print(f"missing Python module: {error.name} (install python3-yaml and python3-jsonschema)")
    sys.exit(2)

JSON_TYPES = ("application/json", "application/problem+json")


def resolve(doc, node):
    """Follows a {"$ref": "#/..."} object (responses, parameters) to what it names."""
    seen = 0
    while isinstance(node, dict) and set(node) == {"$ref"}:
        ref = node["$ref"]
        if not ref.startswith("#/"):
            raise ValueError(f"external $ref {ref!r} is not supported")
        node = doc
        for part in ref[2:].split("/"):
            node = node[part.replace("~1", "/").replace("~0", "~")]
        seen += 1
        if seen > 32:
            raise ValueError(f"$ref loop at {ref!r}")
    return node


def validator(doc, schema):
    """A 2020-12 validator of `schema` whose "#/components/..." references resolve in `doc`."""
    root = dict(schema)
    root["components"] = doc.get("components", {})
    return jsonschema.Draft202012Validator(root)


def problems_of(doc, schema, instance):
    return [f"{'/'.join(str(p) for p in e.absolute_path) or '(root)'}: {e.message}"
            for e in validator(doc, schema).iter_errors(instance)]


def check_examples(doc):
    problems = []
    for name, schema in doc.get("components", {}).get("schemas", {}).items():
        if "example" in schema:
            for p in problems_of(doc, schema, schema["example"]):
                problems.append(f"example of schema {name}: {p}")
    for path, item in doc.get("paths", {}).items():
        for method, operation in item.items():
            if not isinstance(operation, dict) or method == "parameters":
                continue
            bodies = []
            if "requestBody" in operation:
                bodies.append(("request body", resolve(doc, operation["requestBody"])))
            for status, response in operation.get("responses", {}).items():
                bodies.append((f"response {status}", resolve(doc, response)))
            for what, body in bodies:
                for media, content in body.get("content", {}).items():
                    if "example" in content and "schema" in content:
                        for p in problems_of(doc, content["schema"], content["example"]):
                            problems.append(f"{method.upper()} {path} {what} {media} example: {p}")
    return problems


def check_capture(doc, capture):
    where = f"{capture['method']} {capture['route']} -> {capture['status']}"
    item = doc.get("paths", {}).get(capture["route"])
    if item is None:
        return [f"{where}: route not documented"]
    operation = item.get(capture["method"].lower())
    if operation is None:
        return [f"{where}: method not documented"]
    responses = operation.get("responses", {})
    response = responses.get(str(capture["status"]), responses.get("default"))
    if response is None:
        return [f"{where}: status not documented (documented: {', '.join(sorted(responses))})"]
    response = resolve(doc, response)
    content = response.get("content", {})
    media = capture["content_type"].split(";")[0].strip().lower()
    if not content:
        return [] if not capture["body"] else [f"{where}: a body, but the document has no content"]
    if media not in content:
        return [f"{where}: media type {media!r} not documented (documented: {', '.join(content)})"]
    if media not in JSON_TYPES:
        return []
    try:
        body = json.loads(capture["body"])
    except json.JSONDecodeError as error:
        return [f"{where}: body is not JSON: {error}"]
    schema = content[media].get("schema")
    if schema is None:
        return [f"{where}: no schema for {media}"]
    return [f"{where}: {p}" for p in problems_of(doc, schema, body)]


def main(argv):
    if len(argv) not in (2, 3):
        print(__doc__)
        return 2
    with open(argv[1], encoding="utf-8") as f:
        doc = yaml.safe_load(f)
    problems = check_examples(doc)
    checked = 0
    if len(argv) == 3:
        with open(argv[2], encoding="utf-8") as f:
            captures = json.load(f)
        for capture in captures:
            problems += check_capture(doc, capture)
        checked = len(captures)
    for p in problems:
        print(p)
    print(f"openapi_check: {checked} answers checked, {len(problems)} problems")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))

#!/usr/bin/env python3
"""Checks what an lcmx foxglove client saw (fg_client.js's dump): every advertised schema is a
valid JSON Schema (Draft 2020-12) within what Foxglove's and Lichtblick's readers accept (root
object, one `type` string per field, no `$ref`, no arrays of arrays), and every received message
matches its channel's schema. Usage: schema_check.py DUMP.json. Prints one line per channel and
"N passed, M failed"; exit 0 when all pass."""
import json
import sys

import jsonschema


def foxglove_shape(schema, path="#"):
    """Errors of the shape Foxglove's JSON Schema reader needs."""
    errs = []
    if "$ref" in schema:
        errs.append(path + ": $ref")
    t = schema.get("type")
    if not isinstance(t, str):
        errs.append(path + ": type is not one string: %r" % (t,))
        return errs
    if t == "object":
        for k, v in schema.get("properties", {}).items():
            errs += foxglove_shape(v, path + "/" + k)
    elif t == "array":
        items = schema.get("items")
        if not isinstance(items, dict):
            errs.append(path + ": array without items")
        elif items.get("type") == "array":
            errs.append(path + ": array of arrays")
        else:
            errs += foxglove_shape(items, path + "[]")
    return errs


def main():
    dump = json.load(open(sys.argv[1]))
    passed = failed = 0
    for ch in dump["channels"]:
        problems = []
        try:
            schema = json.loads(ch["schema"])
            jsonschema.Draft202012Validator.check_schema(schema)
            if schema.get("type") != "object":
                problems.append("root is not an object")
            problems += foxglove_shape(schema)
            if ch.get("encoding") != "json" or ch.get("schemaEncoding") != "jsonschema":
                problems.append("encoding %s / %s" % (ch.get("encoding"), ch.get("schemaEncoding")))
            v = jsonschema.Draft202012Validator(schema)
            msgs = dump["messages"].get(ch["topic"], [])
            for m in msgs:
                for e in v.iter_errors(m):
                    problems.append("message: " + e.message[:200])
        except Exception as e:  # noqa: BLE001 - any failure is a failed channel
            problems.append(repr(e))
        n = len(dump["messages"].get(ch["topic"], []))
        if problems:
            failed += 1
            print("FAIL %s (%s): %s" % (ch["topic"], ch["schemaName"], "; ".join(problems)))
        else:
            passed += 1
            print("ok   %s (%s), %d message(s) checked" % (ch["topic"], ch["schemaName"], n))
    print("%d passed, %d failed" % (passed, failed))
    return 0 if failed == 0 and passed > 0 else 1


if __name__ == "__main__":
    sys.exit(main())

"""schemathesis hooks of tests/openapi_contract.rs (loaded through SCHEMATHESIS_HOOKS).

The fresh Idempotency-Key per call (idempotency_hooks); `GET /v1/compare`'s cases with two
different arms; and a log of every failure a check
reports, one JSON line each, in the file UFOPS_SCHEMATHESIS_FAILURES names: the test reads it
to tell the failures it accepts (a 428 for a missing If-Match, the documented 422 of a reused
Idempotency-Key) from any other. The hook keeps every failure: the run's own summary counts
them all.
"""
import json
import os

import schemathesis

import idempotency_hooks  # noqa: F401  (registers its hook)


def _problem_type(response):
    try:
        body = response.json()
    except Exception:  # not JSON: no problem document
        return None
    return body.get("type") if isinstance(body, dict) else None


@schemathesis.hook.apply_to(operation_id="get_compare")
def filter_case(context, case):
    """GET /v1/compare refuses arm B = arm A (a 400): a rule between two parameters, which
    OpenAPI cannot state (JSON Schema compares no two values), so the document says it in `b`'s
    description and the cases that should be valid keep to it here. Negative cases are refused
    either way."""
    meta = case.meta
    if meta is not None and meta.generation.mode.is_negative:
        return True
    query = case.query or {}
    return "a" not in query or query.get("a") != query.get("b")


@schemathesis.hook
def filter_failure(context, failure, case, response):
    path = os.environ.get("UFOPS_SCHEMATHESIS_FAILURES")
    if path:
        meta = case.meta
        record = {
            "operation": case.operation.label,
            "check": failure.__class__.__name__,
            "title": failure.title,
            "message": failure.message,
            "status": response.status_code if response is not None else None,
            "problem_type": _problem_type(response) if response is not None else None,
            "header": getattr(failure, "header_name", None),
            "phase": str(getattr(meta.phase.name, "value", meta.phase.name)) if meta is not None else None,
            "negative": bool(meta is not None and meta.generation.mode.is_negative),
            "idempotency_key": (case.headers or {}).get("Idempotency-Key"),
        }
        with open(path, "a", encoding="utf-8") as f:
            f.write(json.dumps(record, default=str) + "\n")
    return True
